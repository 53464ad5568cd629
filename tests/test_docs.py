"""The README and the documentation site, executed, so the text cannot rot.

Conventions (stated for writers in docs/index.md, "How these pages are tested"):

* Every fenced block is ```python, ```text, ```bash or ```console; any other fence fails.
* Every ```python block runs, each in a fresh namespace (blocks share no variables), and must be
  followed directly (blank lines only in between) by a ```text block: its expected stdout. It
  runs as a user runs it, without the suite's tape-access verification (tests/conftest.py).
* In a ```bash block, each command that runs a scene (``tunnelsim ...``, ``.venv/bin/tunnelsim
  ...``, ``python -m scenes ...`` or ``.venv/bin/python -m scenes ...``) runs; it must exit with
  status 0 and write the file its ``--out`` names. A ```text block directly after the ```bash
  block is the expected stdout of its last scene command. Other commands in bash blocks
  (``make``, ``rerun``, ``git``, ``cd``) are not run. ```console blocks show long runs (minutes
  to hours: optimisations, benchmarks) and are not run.
* The blocks of one page run in order in one temporary folder (the working directory of its
  Python blocks and its commands), so a block can read a file an earlier block of the page wrote.
* Expected output is compared token by token: ``...`` matches any run of tokens; a number matches
  when it is within ``REL_TOL`` of the stated one, or within half a unit of its last stated digit,
  whichever is looser; every other token must be equal. Lines Warp prints when it compiles or
  loads a kernel module ("Module ... load on device ... took ...") are not part of the output.

The site build runs ``mkdocs build --strict`` (warnings are errors) into a temporary folder.
"""

from __future__ import annotations

import contextlib
import io
import os
import re
import shlex
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md"] + sorted((ROOT / "docs").rglob("*.md"))
LANGUAGES = {"python", "text", "bash", "console"}
REL_TOL = 1e-2
"""Relative tolerance of a stated number (or half a unit of its last stated digit, if looser)."""
SCENE_TIMEOUT_S = 120

_FENCE = re.compile(r"^```(\S*)\s*$")
_NUMBER = r"[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?"
_TOKEN = re.compile(rf"\.\.\.|{_NUMBER}|[A-Za-z_]+|\S")
_WARP_MODULE_LINE = re.compile(r"^Module \S+( \S+)? load on device .* took .*$")


@dataclass
class Block:
    page: Path
    line: int  # 1-based line of the opening fence
    lang: str
    text: str
    output: "Block | None" = None

    @property
    def where(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def fenced_blocks(page: Path) -> list[Block]:
    """The fenced blocks of a page, each python or bash block linked to the text block that
    directly follows it."""
    blocks: list[Block] = []
    lines = page.read_text().splitlines()
    i = 0
    last_end = None  # line index after the previous block's closing fence
    while i < len(lines):
        m = _FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        start = i
        j = i + 1
        while j < len(lines) and lines[j].strip() != "```":
            j += 1
        assert j < len(lines), f"{page.name}:{start + 1}: unclosed code fence"
        block = Block(page, start + 1, m.group(1), "\n".join(lines[start + 1:j]) + "\n")
        adjacent = last_end is not None and all(not line.strip() for line in lines[last_end:start])
        if block.lang == "text" and adjacent and blocks and blocks[-1].lang in ("python", "bash"):
            blocks[-1].output = block
        blocks.append(block)
        last_end = j + 1
        i = j + 1
    return blocks


def all_blocks() -> list[Block]:
    return [b for page in PAGES for b in fenced_blocks(page)]


# ------------------------------------------------------------------------------ output matching


def tokens(text: str) -> list[str]:
    kept = [line for line in text.splitlines() if not _WARP_MODULE_LINE.match(line.strip())]
    return _TOKEN.findall("\n".join(kept))


def _is_number(token: str) -> bool:
    return re.fullmatch(_NUMBER, token) is not None


def _half_unit(token: str) -> float:
    """Half a unit in the last digit written: 0.25 -> 0.005, 4e-5 -> 0.5e-5, 120 -> 0.5."""
    mantissa, _, exponent = token.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 0.5 * 10.0 ** (-decimals + (int(exponent) if exponent else 0))


def same_token(expected: str, actual: str) -> bool:
    if _is_number(expected) and _is_number(actual):
        e, a = float(expected), float(actual)
        return abs(a - e) <= max(REL_TOL * abs(e), _half_unit(expected))
    return expected == actual


def matches(expected: list[str], actual: list[str]) -> bool:
    """Whether ``actual`` matches ``expected``, where ``...`` in ``expected`` matches any run of
    tokens (dynamic programming over the two positions)."""
    n, m = len(expected), len(actual)
    ok = [[False] * (m + 1) for _ in range(n + 1)]
    ok[n][m] = True
    for i in range(n - 1, -1, -1):
        for j in range(m, -1, -1):
            if expected[i] == "...":
                ok[i][j] = ok[i + 1][j] or (j < m and ok[i][j + 1])
            else:
                ok[i][j] = j < m and same_token(expected[i], actual[j]) and ok[i + 1][j + 1]
    return ok[0][0]


def check_output(block: Block, actual: str) -> None:
    expected = block.output.text
    assert matches(tokens(expected), tokens(actual)), (
        f"{block.where}: the output differs from the stated one ({block.output.where}), numbers "
        f"within {REL_TOL:g} relative or the digits shown\n--- stated:\n{expected}--- actual:\n{actual}")


# ------------------------------------------------------------------------------ running blocks


def scene_commands(block: Block) -> list[list[str]]:
    """The scene commands of a bash block (continuation lines joined), as argument lists with
    the executable replaced by this interpreter's."""
    joined = re.sub(r"\\\n", " ", block.text)
    bin_dir = Path(sys.executable).parent
    commands = []
    for line in joined.splitlines():
        line = line.split(" #", 1)[0].strip()
        if not line or line.startswith("#"):
            continue
        argv = shlex.split(line)
        if argv[0] in ("tunnelsim", ".venv/bin/tunnelsim"):
            commands.append([str(bin_dir / "tunnelsim")] + argv[1:])
        elif argv[0] in ("python", ".venv/bin/python") and argv[1:3] == ["-m", "scenes"]:
            commands.append([sys.executable] + argv[1:])
    return commands


def out_path(argv: list[str]) -> str | None:
    return argv[argv.index("--out") + 1] if "--out" in argv else None


BLOCKS = all_blocks()
PYTHON = [b for b in BLOCKS if b.lang == "python"]
SCENE_BLOCKS = [b for b in BLOCKS if b.lang == "bash" and scene_commands(b)]
RUNNABLE = [b for b in BLOCKS if b in PYTHON or b in SCENE_BLOCKS]  # page by page, in page order


def test_blocks_follow_the_conventions():
    """Known fence languages only; every python block has its output; the README has python
    and scene blocks (the three examples)."""
    bad = [f"{b.where}: ```{b.lang}" for b in BLOCKS if b.lang not in LANGUAGES]
    assert not bad, f"fences must be one of {sorted(LANGUAGES)}: {bad}"
    missing = [b.where for b in PYTHON if b.output is None]
    assert not missing, f"python blocks without a ```text output block right after them: {missing}"
    readme = [b for b in BLOCKS if b.page.name == "README.md"]
    assert sum(b.lang == "python" for b in readme) >= 2 and any(b in SCENE_BLOCKS for b in readme)


def run_python(block: Block, cwd: Path, monkeypatch) -> None:
    """Runs as a user runs it: without the suite's tape-access verification (tests/conftest.py),
    which checks the simulator's own gradient tests and makes a taped rollout about 15x slower."""
    import warp as wp

    monkeypatch.setattr(wp.config, "verify_autograd_array_access", False)
    monkeypatch.chdir(cwd)
    out = io.StringIO()
    namespace = {"__name__": "__main__"}
    with contextlib.redirect_stdout(out):
        exec(compile(block.text, block.where, "exec"), namespace)
    check_output(block, out.getvalue())


def run_scenes(block: Block, cwd: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    for argv in scene_commands(block):
        out = out_path(argv)
        assert out is not None, f"{block.where}: a scene command without --out: {shlex.join(argv)}"
        run = subprocess.run(argv, cwd=cwd, env=env, capture_output=True, text=True, timeout=SCENE_TIMEOUT_S)
        assert run.returncode == 0, f"{block.where}: {shlex.join(argv)} exited {run.returncode}\n{run.stderr[-3000:]}"
        assert (cwd / out).is_file() and (cwd / out).stat().st_size > 0, f"{block.where}: no {out} written"
    if block.output is not None:
        check_output(block, run.stdout)


@pytest.mark.parametrize("page", sorted({b.page for b in RUNNABLE}), ids=lambda p: str(p.relative_to(ROOT)))
def test_page_examples_run_and_print_their_stated_output(page, tmp_path, monkeypatch):
    """The page's python blocks print their stated output, and its bash blocks' scene commands
    exit 0, write their recordings and print the stated output; in page order, in one folder."""
    for block in (b for b in RUNNABLE if b.page == page):
        if block.lang == "python":
            run_python(block, tmp_path, monkeypatch)
        else:
            run_scenes(block, tmp_path)


def test_docs_build_strict(tmp_path):
    """``mkdocs build --strict``: a broken link, a missing page in the navigation or a
    docstring the API reference cannot parse is an error."""
    run = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path / "site")],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    log = run.stdout + run.stderr
    assert run.returncode == 0 and "WARNING" not in log, log[-5000:]
    site = tmp_path / "site"
    guides = [p.stem for p in (ROOT / "docs").glob("*.md") if p.stem != "index"]
    for page in ["index.html"] + [f"{g}/index.html" for g in guides]:
        assert (site / page).is_file(), f"{page} not built"
    api = (site / "api" / "rollout" / "index.html").read_text()
    assert 'id="sim.rollout.rollout"' in api and "particle_qd" in api, "the API reference lacks rollout's docstring"


def test_output_matching_rules():
    """The matcher itself: tolerance, digits, ellipsis, and a mismatch that must fail."""
    assert matches(tokens("loss 0.26 -> 4e-5"), tokens("loss 0.2634 -> 4.3e-5"))
    assert not matches(tokens("loss 0.26"), tokens("loss 0.28"))
    assert matches(tokens('{"steps": 120, ... "penetrations": 0, ...}'),
                   tokens('{"steps": 120, "wall": 2.5, "penetrations": 0, "out": "a.rrd"}'))
    assert not matches(tokens('{"penetrations": 0}'), tokens('{"penetrations": 3}'))
    assert matches(tokens("dy/dv0: [0.0, -0.25, 0.0]"), tokens("dy/dv0: [0.0, -0.2500000001, 1e-20]"))
    assert not matches(tokens("hit: True"), tokens("hit: False"))
    assert tokens("Module kernels.ccd 852f59b load on device 'cpu' took 5.7 ms  (compiled)\nok 1") == ["ok", "1"]
