"""The argument parsers of the project's commands and scripts, got without running them (used by the docs tests).

A repository script (``examples/x.py``, ``benchmarks/x.py``) builds its parser inside ``main()``; to parse the
arguments the documentation gives it with that very parser, :func:`script_parser` imports the script (not as
``__main__``) and calls its entry point with ``ArgumentParser.parse_args`` replaced by a function that hands
the parser back and stops there, so nothing after the parsing runs. The commands (``attnloop-slam``,
``attnloop-eval``) expose ``build_parser()``.

Run as a script, it answers a list of jobs given as JSON on stdin, one result per job as JSON on stdout, in
a fresh interpreter (a script's import-time settings, such as its torch threads, stay out of the test's):

* ``{"job": "parse", "command": "examples/x.py", "argv": [...]}``: ``{"ok": bool, "error": str}``, the
  arguments parsed by the command's real parser (``--help`` counts as ok).
* ``{"job": "help", "command": "examples/x.py"}``: ``{"exit_code": int, "help": str, "no_help": [...],
  "formatter": str, "multiline_description": bool}``: the script run as ``python x.py --help`` would be (in
  this interpreter), the options whose help string is missing, and whether the description or epilog has
  line breaks of its own (which only a raw formatter keeps), and every option string.
* ``{"job": "options", "command": ...}``: ``{"options": [...]}``, every option string, subcommands' included.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import io
import json
import os
import re
import runpy
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]

#: installed commands (pyproject's [project.scripts]) and the module that builds each one's parser
COMMANDS = {"attnloop-slam": "slam.cli", "attnloop-eval": "slam.eval.cli"}


class _Captured(Exception):
    def __init__(self, parser: argparse.ArgumentParser):
        super().__init__("parser captured")
        self.parser = parser


def _load(path: Path):
    spec = importlib.util.spec_from_file_location(f"_docs_script_{path.stem}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses of the script look their module up there
    spec.loader.exec_module(module)
    return module


def script_parser(command: str) -> argparse.ArgumentParser:
    """The parser of ``command``: an installed command's name or a script's path relative to the repository."""
    if command in COMMANDS:
        return importlib.import_module(COMMANDS[command]).build_parser()
    path = ROOT / command
    if not path.is_file():
        raise FileNotFoundError(f"{command}: no such script in the repository")
    for folder in (str(ROOT), str(path.parent)):  # as ``python x.py`` has it: the script's folder first
        if folder not in sys.path:
            sys.path.insert(0, folder)
    module = _load(path)
    entry = next((getattr(module, n) for n in ("build_parser", "parse_args", "main") if hasattr(module, n)), None)
    if entry is None:
        raise LookupError(f"{command} has no build_parser(), parse_args() or main()")
    original = argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args

    def capture(self, *args, **kwargs):
        raise _Captured(self)

    argparse.ArgumentParser.parse_args = argparse.ArgumentParser.parse_known_args = capture
    argv = sys.argv
    sys.argv = [str(path)]
    try:
        out = entry()
    except _Captured as c:
        return c.parser
    finally:
        argparse.ArgumentParser.parse_args, argparse.ArgumentParser.parse_known_args = original
        sys.argv = argv
    if isinstance(out, argparse.ArgumentParser):  # build_parser()
        return out
    raise LookupError(f"{command}: {entry.__name__}() returned without parsing arguments")


def _all_parsers(parser: argparse.ArgumentParser) -> list[argparse.ArgumentParser]:
    found = [parser]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                found.extend(_all_parsers(sub))
    return found


def option_strings(parser: argparse.ArgumentParser) -> list[str]:
    return sorted({s for p in _all_parsers(parser) for a in p._actions for s in a.option_strings})


def options_without_help(parser: argparse.ArgumentParser) -> list[str]:
    """Every argument (options and positionals, subcommands' included) whose help string is missing."""
    missing = []
    for p in _all_parsers(parser):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction) or a.help == argparse.SUPPRESS:
                continue
            if not (a.help or "").strip():
                missing.append(f"{p.prog}: {'/'.join(a.option_strings) or a.dest}")
    return missing


def parse(command: str, argv: list[str]) -> dict:
    """``argv`` parsed by ``command``'s parser: ``{"ok": True}`` or ``{"ok": False, "error": message}``."""
    parser = script_parser(command)
    messages = []

    def error(self, message):  # argparse's usage error, as an exception instead of exit code 2
        raise ValueError(f"{self.prog}: {message}")

    for p in _all_parsers(parser):
        p.error = error.__get__(p)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            parser.parse_args(argv)
    except SystemExit as e:  # --help, --version
        if e.code not in (0, None):
            messages.append(f"exit code {e.code}")
    except ValueError as e:
        messages.append(str(e))
    return {"ok": not messages, "error": "; ".join(messages)}


def _has_own_lines(text) -> bool:
    """A text with paragraphs, list items or indented lines: what argparse's default formatter would reflow."""
    return bool(text) and re.search(r"\n\s*\n|\n[ \t]+\S|\n\s*[-*] ", text.strip()) is not None


def run_help(command: str) -> dict:
    """``command --help`` as the shell would run it, in this interpreter; plus the parser's help checks."""
    parser = script_parser(command)
    texts = [t for p in _all_parsers(parser) for t in (p.description, p.epilog) if t]
    raw = all(issubclass(p.formatter_class, argparse.RawDescriptionHelpFormatter) for p in _all_parsers(parser)
              if any(_has_own_lines(t) for t in (p.description, p.epilog)))
    out, argv = io.StringIO(), sys.argv
    code = None
    with contextlib.redirect_stdout(out):
        try:
            if command in COMMANDS:
                importlib.import_module(COMMANDS[command]).main(["--help"])
            else:
                sys.argv = [str(ROOT / command), "--help"]
                runpy.run_path(str(ROOT / command), run_name="__main__")
            code = 0
        except SystemExit as e:
            code = 0 if e.code is None else e.code if isinstance(e.code, int) else 1
        finally:
            sys.argv = argv
    return {"exit_code": code, "help": out.getvalue(), "no_help": options_without_help(parser),
            "options": option_strings(parser),
            "raw_where_needed": raw, "multiline_description": any("\n" in t.strip() for t in texts)}


def ask(jobs: list[dict]) -> list[dict]:
    """Answers of tests/docs/docs_commands.py to ``jobs``, in a fresh interpreter (one per call)."""
    if not jobs:
        return []
    env = dict(os.environ, OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]))
    r = subprocess.run([sys.executable, str(ROOT / "tests" / "docs" / "docs_commands.py")], input=json.dumps(jobs),
                       capture_output=True, text=True, cwd=ROOT, env=env, timeout=600, check=False)
    assert r.returncode == 0 and "@@RESULTS@@" in r.stdout, f"docs_commands.py failed:\n{r.stderr[-3000:]}"
    return json.loads(r.stdout.rsplit("@@RESULTS@@", 1)[1])


def main() -> int:
    jobs = json.load(sys.stdin)
    results = []
    for job in jobs:
        try:
            if job["job"] == "parse":
                results.append(parse(job["command"], job["argv"]))
            elif job["job"] == "help":
                results.append(run_help(job["command"]))
            else:
                results.append({"options": option_strings(script_parser(job["command"]))})
        except Exception as e:  # noqa: BLE001 (reported per job, the others still answered)
            results.append({"ok": False, "error": f"{type(e).__name__}: {e}", "exception": True})
    sys.stdout.write("\n@@RESULTS@@" + json.dumps(results))
    return 0


if __name__ == "__main__":
    sys.exit(main())
