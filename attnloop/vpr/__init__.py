"""Place recognition on image collections: describe, index, query, evaluate (the ``attnloop-vpr`` command).
"""
