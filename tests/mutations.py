"""Seeded mutations of real input files, shared by the fuzz tests (readers, CLI).

``mutate(data, kind, rng)`` returns a mutated copy of the bytes of a file; :data:`MUTATIONS` lists the
kinds. Each kind models a way files from the wild go wrong: cut short, a corrupted byte, a byte that is
not UTF-8, a number replaced by NaN / inf / a huge value, a line with a field too many or too few, an
empty file, a repeated line, comments (whole-line and trailing), Windows line endings and a byte-order
mark, text where a number belongs. ``rng`` is a :class:`random.Random`, so a case is reproduced from its
seed.

Example:
    >>> import random
    >>> mutate(b"1.0 2.0 3.0\\n", "huge_number", random.Random(0)) != b"1.0 2.0 3.0\\n"
    True
"""
from __future__ import annotations

import random
import re

__all__ = ["MUTATIONS", "mutate"]

_NUMBER = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
_BAD_NUMBERS = (b"nan", b"inf", b"-inf", b"NaN", b"1e309")
_HUGE_NUMBERS = (b"1e300", b"-1e300", b"1e200", b"1e20", b"100000000000000000000", b"1e-320", b"9" * 400)
_NOT_UTF8 = (b"\xff", b"\xfe", b"\xe9", b"\xc3\x28", b"\x80", b"\xed\xa0\x80")


def _lines(data: bytes) -> list:
    return data.split(b"\n")


def _numbers(data: bytes) -> list:
    return list(_NUMBER.finditer(data))


def _replace_number(data: bytes, rng: random.Random, choices) -> bytes:
    found = _numbers(data)
    if not found:
        return data + rng.choice(choices)
    m = rng.choice(found)
    return data[:m.start()] + rng.choice(choices) + data[m.end():]


def _content_lines(lines: list) -> list:
    return [k for k, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith(b"#")] or [0]


def _truncate(data, rng):
    return data[:rng.randrange(len(data) + 1)] if data else data


def _flip_byte(data, rng):
    if not data:
        return bytes([rng.randrange(256)])
    k = rng.randrange(len(data))
    return data[:k] + bytes([data[k] ^ (1 << rng.randrange(8))]) + data[k + 1:]


def _not_utf8(data, rng):
    k = rng.randrange(len(data) + 1)
    return data[:k] + rng.choice(_NOT_UTF8) + data[k:]


def _field_count(data, rng):
    lines = _lines(data)
    k = rng.choice(_content_lines(lines))
    fields = lines[k].split()
    if fields and rng.random() < 0.5:
        fields.pop(rng.randrange(len(fields)))
    else:
        fields.insert(rng.randrange(len(fields) + 1), rng.choice([b"0", b"1.5", b"7"]))
    lines[k] = b" ".join(fields)
    return b"\n".join(lines)


def _duplicate_line(data, rng):
    lines = _lines(data)
    k = rng.choice(_content_lines(lines))
    lines.insert(k + rng.choice([0, 1, 2]), lines[k])
    return b"\n".join(lines)


def _comments(data, rng):
    lines = _lines(data)
    k = rng.choice(_content_lines(lines))
    if rng.random() < 0.5:
        lines[k] = lines[k] + rng.choice([b" # trailing comment", b"\t#x", b" #"])
    else:
        lines.insert(k, rng.choice([b"# a comment", b"   # indented", b"#", b""]))
    return b"\n".join(lines)


def _text_for_number(data, rng):
    return _replace_number(data, rng, (b"x", b"one", b"1,5", b"--1", b"0x10", b"1.2.3", b""))


def _line_endings(data, rng):
    out = data.replace(b"\n", b"\r\n") if rng.random() < 0.5 else data.replace(b"\n", b"\r")
    return (b"\xef\xbb\xbf" + out) if rng.random() < 0.5 else out


def _swap_lines(data, rng):
    lines = _lines(data)
    idx = _content_lines(lines)
    a, b = rng.choice(idx), rng.choice(idx)
    lines[a], lines[b] = lines[b], lines[a]
    return b"\n".join(lines)


_KINDS = {
    "truncate": _truncate,
    "flip_byte": _flip_byte,
    "not_utf8": _not_utf8,
    "non_finite": lambda d, r: _replace_number(d, r, _BAD_NUMBERS),
    "huge_number": lambda d, r: _replace_number(d, r, _HUGE_NUMBERS),
    "field_count": _field_count,
    "empty": lambda d, r: b"" if r.random() < 0.5 else b"\n\n# only a comment\n",
    "duplicate_line": _duplicate_line,
    "comments": _comments,
    "text_for_number": _text_for_number,
    "line_endings": _line_endings,
    "swap_lines": _swap_lines,
}

# the kinds of mutation, in a fixed order
MUTATIONS = tuple(_KINDS)


def mutate(data: bytes, kind: str, rng: random.Random) -> bytes:
    """A mutated copy of ``data`` (the bytes of a file); ``kind`` is one of :data:`MUTATIONS`."""
    if kind not in _KINDS:
        raise ValueError(f"kind must be one of {MUTATIONS}, got {kind!r}")
    return _KINDS[kind](bytes(data), rng)
