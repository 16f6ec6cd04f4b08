"""The documentation runs: ``mkdocs build --strict``, and every code block of the README and of
``docs/`` executed as ``docs/reference/docs-tests.md`` describes (commands with
``experiment=smoke`` appended, Python files written where a block names one, outputs compared).
"""

from __future__ import annotations

import functools
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from cli_server import ONE_THREAD, plain_command, shared_server

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
PAGES = [ROOT / "README.md"] + sorted(
    p for p in DOCS.rglob("*.md") if p.relative_to(DOCS).parts[0] not in ("tables", "hooks")
)
FENCE = re.compile(
    r"^(?P<indent> *)```(?P<lang>[\w-]*)(?P<info>[^\n]*)\n(?P<body>.*?)^(?P=indent)```[ \t]*$",
    re.M | re.S,
)
SKIP = re.compile(r"<!-- docs-test: skip (?P<reason>.+?) -->\s*$")
INSTALL = re.compile(r"^(python3? -m venv |\. \.venv/bin/activate|pip install )")
TRAINS = ("stages-train", "stages-tune")
TIMEOUT = 900
HAS_MKDOCS = shutil.which("mkdocs") is not None or (Path(sys.executable).parent / "mkdocs").exists()


@dataclass
class Block:
    page: Path
    line: int
    lang: str
    title: str | None
    body: str
    skip: str | None  # the reason, for a block marked not to run


def blocks(page: Path) -> list[Block]:
    """The fenced blocks of ``page``, in order."""
    text = page.read_text()
    found = []
    for match in FENCE.finditer(text):
        indent = len(match["indent"])
        body = "\n".join(line[indent:] for line in match["body"].splitlines())
        title = re.search(r'title="([^"]+)"', match["info"])
        before = text[: match.start()].rstrip("\n").splitlines()
        skip = SKIP.search(before[-1]) if before else None
        found.append(
            Block(
                page,
                text.count("\n", 0, match.start()) + 1,
                match["lang"],
                title[1] if title else None,
                body + "\n",
                skip["reason"] if skip else None,
            )
        )
    return found


def commands(body: str) -> list[str]:
    """The commands of a bash block: continued lines joined, comments dropped."""
    joined = re.sub(r"\s*\\\n\s*", " ", body)
    found = []
    for line in joined.splitlines():
        line = _strip_comment(line).strip()
        if line:
            found.append(line)
    return found


def _strip_comment(line: str) -> str:
    quote = None
    for i, char in enumerate(line):
        if char in "'\"" and quote in (None, char):
            quote = None if quote else char
        elif char == "#" and quote is None and (i == 0 or line[i - 1].isspace()):
            return line[:i]
    return line


def installed(command: str) -> str:
    """``command`` without its install steps."""
    return " && ".join(p for p in command.split(" && ") if not INSTALL.match(p.strip()))


def runnable(command: str, number: int) -> str | None:
    """``command`` as the test runs it: install steps dropped, training shortened to
    ``experiment=smoke`` (after the command's own preset: ``experiment=[<preset>,smoke]``) in a
    run directory of its own; ``None`` when nothing is left."""
    out = []
    for part in filter(None, installed(command).split(" && ")):
        words = part.split()
        program = next((w for w in words if "=" not in w), "")
        if program in TRAINS and "--help" not in words and "--cfg" not in words:
            preset = next((w for w in words if w.startswith("experiment=")), None)
            if preset is None:
                part += " experiment=smoke"
            elif preset != "experiment=smoke":  # a preset of its own, shortened by smoke's
                part = part.replace(preset, f"{preset.replace('=', '=[', 1)},smoke]")
            if not any(w.startswith("eval.plots=") for w in words):
                part += " eval.plots=false"  # the figures are tested apart; here they cost time
            if program == "stages-train":
                key = "hydra.sweep.dir" if "-m" in words else "hydra.run.dir"
                if not any(w.startswith(key + "=") for w in words):
                    part += f" {key}={'multirun' if '-m' in words else 'outputs'}/cmd{number}"
        out.append(part)
    return " && ".join(out) or None


def matches(expected: str, actual: str) -> bool:
    """The expected lines appear in order among the actual ones; ``...`` matches any text."""
    lines = actual.splitlines()
    position = 0
    for want in expected.strip("\n").splitlines():
        pattern = re.compile(".*".join(re.escape(p) for p in want.strip().split("...")))
        while position < len(lines) and not pattern.fullmatch(lines[position].strip()):
            position += 1
        if position == len(lines):
            return False
        position += 1
    return True


def _env(scratch: Path) -> dict[str, str]:
    env = dict(os.environ)
    env["HOME"] = str(scratch)  # ~/stages and the like stay in the scratch directory
    env["PATH"] = f"{Path(sys.executable).parent}{os.pathsep}{env.get('PATH', '')}"
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(scratch), env.get("PYTHONPATH")]))
    env.update(ONE_THREAD)  # a block's own torch code too: pytest workers share the cores
    env.pop("PYTEST_CURRENT_TEST", None)
    return env


def _run(args: list[str], scratch: Path, where: str) -> subprocess.CompletedProcess:
    try:
        return subprocess.run(
            args, cwd=scratch, env=_env(scratch), capture_output=True, text=True, timeout=TIMEOUT
        )
    except subprocess.TimeoutExpired as error:
        pytest.fail(f"{where}: did not finish in {TIMEOUT} s: {error}")


def _run_shell(command: str, scratch: Path, where: str) -> subprocess.CompletedProcess:
    """``bash -c command``; a plain console-script command runs in a fork of a process that
    has imported the package instead (``cli_server``: the same argv, directory, environment
    and exit status, without the 4 s import)."""
    plain = plain_command(command, _env(scratch), scratch)
    if plain is None:
        return _run(["bash", "-c", command], scratch, where)
    assignments, argv = plain
    return _run_forked(argv, scratch, where, assignments)


def _run_forked(
    argv: list[str], scratch: Path, where: str, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess:
    """A console script, or ``python script`` (``argv[0]`` a ``.py`` file: the script as
    ``__main__``, as the benchmark scripts' tests run them), in a fork of the process that has
    imported the package (``cli_server``), in ``scratch`` with ``env`` over its environment."""
    try:
        return shared_server().run(argv, scratch, {**_env(scratch), **(env or {})}, TIMEOUT)
    except subprocess.TimeoutExpired as error:
        pytest.fail(f"{where}: did not finish in {TIMEOUT} s: {error}")


#: top-level keys whose value names other runs or Hydra's directories: a command that sets one
#: reads or writes state that the commands around it share, and always runs on its own page
STATEFUL = {"hydra", "init_from", "resume", "stage_store"}


def standalone(command: str) -> bool:
    """``command`` is a plain ``stages-train`` run of config overrides (or ``--help``) that
    reads nothing a page wrote before it but files it wrote, and writes a run directory no
    other command reads: run twice, it does the same thing."""
    plain = plain_command(command)
    if plain is None or plain[0] or plain[1][0] != "stages-train":
        return False

    def override(word: str) -> bool:
        key, equals, value = word.partition("=")
        top = key.lstrip("+~").split(".")[0].split("@")[0]
        return bool(equals) and top not in STATEFUL and not set("/~$").intersection(value)

    return all(word == "--help" or override(word) for word in plain[1][1:])


@functools.cache
def runs_elsewhere() -> dict[tuple[Path, int, int], str]:
    """The standalone commands (:func:`standalone`, install steps left out) that an earlier
    block runs too, on this page or another, with the same files written before them:
    ``(page, block line, command's number in the block)`` to where the first runs. The suite
    runs each once."""
    first: dict[tuple, str] = {}
    elsewhere = {}
    for page in PAGES:
        written: dict[str, str] = {}
        found = blocks(page)
        for index, block in enumerate(found):
            if block.skip:
                continue
            if block.lang in ("python", "yaml", "toml") and block.title:
                written[block.title] = block.body
            if block.lang != "bash":
                continue
            following = found[index + 1] if index + 1 < len(found) else None
            checked = following is not None and following.title == "output"
            cmds = commands(block.body)
            for number, command in enumerate(cmds):
                run = installed(command)
                if not standalone(run) or (checked and number == len(cmds) - 1):
                    continue
                key = (run, tuple(sorted(written.items())))
                if key in first:
                    elsewhere[(page, block.line, number)] = first[key]
                else:
                    first[key] = f"{page.relative_to(ROOT)}:{block.line}"
    return elsewhere


def run_page(page: Path, scratch: Path) -> list[str]:
    """Runs every block of ``page`` in ``scratch``; returns the reasons of skipped blocks."""
    skipped = []
    found = blocks(page)
    readme_test_command = _readme_commands()[1] if page.name == "README.md" else None
    for index, block in enumerate(found):
        where = f"{page.relative_to(ROOT)}:{block.line}"
        following = found[index + 1] if index + 1 < len(found) else None
        output = following if following and following.title == "output" else None
        if block.skip:
            skipped.append(f"{where}: {block.skip}")
            continue
        if block.lang in ("python", "yaml", "toml") and block.title:
            target = scratch / block.title
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_text(block.body)
            continue
        if block.lang == "python":
            script = scratch / f"_block_{block.line}.py"
            script.write_text(block.body)
            _check(_run_forked([script.name], scratch, where), output, where)
        elif block.lang == "pycon":
            script = scratch / f"_block_{block.line}.txt"
            script.write_text(block.body)
            runner = scratch / f"_block_{block.line}_doctest.py"
            runner.write_text(
                "import doctest, sys\nflags = doctest.ELLIPSIS | doctest.NORMALIZE_WHITESPACE\n"
                f"r = doctest.testfile({script.name!r}, module_relative=False, optionflags=flags)\n"
                "sys.exit(1 if r.failed else 0)\n"
            )
            _check(_run_forked([runner.name], scratch, where), None, where)
        elif block.lang == "bash":
            cmds = commands(block.body)
            for number, command in enumerate(cmds):
                if command == readme_test_command:
                    continue  # the suite itself: .ci/run runs it (test_readme_commands)
                if (page, block.line, number) in runs_elsewhere():
                    continue  # the same run as an earlier block's (runs_elsewhere)
                shell = runnable(command, block.line * 100 + number)
                if shell is None:
                    continue
                done = _run_shell(shell, scratch, f"{where}: {command}")
                last = number == len(cmds) - 1
                _check(done, output if last else None, f"{where}: {command}")
    return skipped


def _check(done: subprocess.CompletedProcess, output: Block | None, where: str) -> None:
    printed = done.stdout + done.stderr
    if output is None:
        assert done.returncode == 0, f"{where}: exit {done.returncode}\n{printed[-4000:]}"
    else:
        assert matches(output.body, printed), (
            f"{where}: the output does not match the block below it\n--- expected\n"
            f"{output.body}\n--- printed (exit {done.returncode})\n{printed[-4000:]}"
        )


def _readme_commands() -> list[str]:
    bash = [b for b in blocks(ROOT / "README.md") if b.lang == "bash"]
    return [commands(b.body)[0] for b in bash[:2]]


# ---------------------------------------------------------------------------------- the tests
def test_every_block_has_a_known_kind():
    """A block the runner does not know would silently not run."""
    known = {"bash", "python", "pycon", "yaml", "toml", "text", ""}
    for page in PAGES:
        for block in blocks(page):
            where = f"{page.relative_to(ROOT)}:{block.line}"
            assert block.lang in known, f"{where}: ```{block.lang} blocks are not run"
            if block.lang in ("yaml", "toml"):
                assert block.title, f'{where}: a {block.lang} block needs title="<path>"'
            if block.title == "output":
                assert block.lang == "text", f"{where}: an output block is ```text"


def test_files_shown_are_the_repository_s():
    """A file a page shows (``title="name.py"``) that the repository keeps too, under
    ``scripts/`` or ``tests/``, is that file: the docs cannot drift from the tested copy."""
    for page in PAGES:
        for block in blocks(page):
            if block.lang != "python" or not block.title:
                continue
            for kept in (ROOT / "scripts" / block.title, ROOT / "tests" / block.title):
                if kept.is_file():
                    where = f"{page.relative_to(ROOT)}:{block.line}"
                    assert block.body == kept.read_text(), f"{where} differs from {kept}"


def test_readme_commands():
    """The README's first command installs and trains; its second is exactly ``.ci/run``'s."""
    first, second = _readme_commands()
    assert first.endswith("pip install . && stages-train"), first
    ci = (ROOT / ".ci" / "run").read_text()
    assert second in ci.splitlines(), f".ci/run does not run the README's test command {second}"
    assert len((ROOT / "README.md").read_text().splitlines()) <= 300


def test_output_matching():
    assert matches("a ... c\nd", "x\na b c\ny\nd\n")
    assert not matches("d\na ... c", "a b c\nd\n")


def test_runnable_commands():
    assert runnable("pip install . && stages-train", 1) == (
        "stages-train experiment=smoke eval.plots=false hydra.run.dir=outputs/cmd1"
    )
    assert runnable("stages-train -m seed=0,1 hydra.sweep.dir=s eval.plots=true", 2) == (
        "stages-train -m seed=0,1 hydra.sweep.dir=s eval.plots=true experiment=smoke"
    )
    assert runnable("python3 -m venv .venv && . .venv/bin/activate", 3) is None
    assert runnable("stages-train experiment=manipulator_td3 hydra.run.dir=r", 4) == (
        "stages-train experiment=[manipulator_td3,smoke] hydra.run.dir=r eval.plots=false"
    )
    assert commands("a \\\n  b  # note\n'#' c\n") == ["a b", "'#' c"]
    assert runnable("stages-tune tune.n_trials=2", 5) == (
        "stages-tune tune.n_trials=2 experiment=smoke eval.plots=false"
    )


def test_a_standalone_command_on_several_pages_runs_once():
    assert standalone("stages-train task=cargo algo@task.stages.fine=td3 task/gammas=hetero")
    assert standalone("stages-train --help") and standalone(
        installed("pip install . && stages-train")
    )
    for stateful in (
        "stages-train hydra.run.dir=runs/a",
        "stages-train task.stages.s1.lr=2e-3 init_from=runs/a",
        "stages-train resume=true",
        "stages-train stage_store=~/stages",
        "stages-train ++init_from=runs_a",
        "stages-train hydra.job.chdir=true",
        "stages-train seeds=[0,1] +task.env.path=data/x.npz",
        "PYTHONPATH=. stages-train task=gym",
        "stages-train -m seed=0,1",
        "stages-eval runs/a",
        "stages-train && stages-eval runs/a",
    ):
        assert not standalone(stateful), stateful
    elsewhere = runs_elsewhere()
    pages = {str(p.relative_to(ROOT)) for p in PAGES}
    shared = []
    for (page, line, number), first in elsewhere.items():
        command = commands(next(b for b in blocks(page) if b.line == line).body)[number]
        assert standalone(installed(command)) and first.split(":")[0] in pages, command
        shared.append((page.name, command))
    assert ("cli.md", "stages-train schedule=joint") in shared


def test_plain_commands_run_in_a_fork_the_rest_in_bash():
    assert plain_command("PYTHONPATH=. stages-train 'a=b c' seeds=[0,1]") == (
        {"PYTHONPATH": "."},
        ["stages-train", "a=b c", "seeds=[0,1]"],
    )
    for shell in ("stages-train && stages-eval r", "stages-report s | head", "python x.py"):
        assert plain_command(shell) is None, shell
    for expansion in ("stages-store ls ~/stages", "stages-store ls $HOME/s", "stages-eval `pwd`"):
        assert plain_command(expansion) is None, expansion  # without the environment to expand
    env = {"HOME": "/h", "PATH": os.environ["PATH"]}
    assert plain_command("X=$HOME stages-store ls ~/s 'a b' '$HOME' \\~ s=~/t", env) == (
        {"X": "/h"},
        ["stages-store", "ls", "/h/s", "a b", "$HOME", "~", "s=/h/t"],
    )
    assert plain_command("stages-eval $(pwd)", env) is None  # a subshell: bash runs it


def test_a_forked_command_is_the_console_script(tmp_path):
    """The same output and exit status as the installed script, in bash, for a good command
    and a refused one."""
    for args in (["--help"], ["task.stages.s2.gamma=1.5"]):
        script = subprocess.run(
            ["bash", "-c", " ".join(["stages-train", *args])],
            cwd=tmp_path,
            env=_env(tmp_path),
            capture_output=True,
            text=True,
            timeout=120,
        )
        forked = shared_server().run(["stages-train", *args], tmp_path, _env(tmp_path), 120)
        assert (forked.returncode, forked.stdout) == (script.returncode, script.stdout)
        assert forked.stderr.splitlines()[-1:] == script.stderr.splitlines()[-1:]


def test_forked_commands_run_side_by_side(tmp_path):
    """Started commands run at once; each result reaches its own job, in any order; a command
    past its timeout, or stopped, is killed and the server goes on."""
    server, env = shared_server(), _env(tmp_path)
    # a stage with no early stop and 10^7 frames: minutes
    long = ["stages-train", "task.stages.s4.frames=10_000_000", "task.stages.s4.eval_every=0"]
    long.append(f"hydra.run.dir={tmp_path / 'long'}")
    stopped = server.start(long, tmp_path, env, 120)
    late = server.start(["stages-train", "task.stages.s2.gamma=1.5"], tmp_path, env, 120)
    timed_out = server.start([*long[:-1], f"hydra.run.dir={tmp_path / 'timed'}"], tmp_path, env, 2)
    helped = server.start(["stages-train", "--help"], tmp_path, env, 120)
    assert server.wait(helped).returncode == 0
    with pytest.raises(subprocess.TimeoutExpired):
        server.wait(timed_out)
    refused = server.wait(late)
    assert refused.returncode != 0 and "task.stages.s2.gamma" in refused.stderr
    assert not (tmp_path / "long" / "eval.json").exists()
    server.kill(stopped)
    assert server.run(["stages-eval", "--help"], tmp_path, env, 120).returncode == 0


@pytest.mark.slow
@pytest.mark.skipif(not HAS_MKDOCS, reason='mkdocs is not installed (pip install -e ".[docs]")')
def test_mkdocs_build_strict(tmp_path):
    mkdocs = Path(sys.executable).parent / "mkdocs"
    done = subprocess.run(
        [str(mkdocs) if mkdocs.exists() else "mkdocs", "build", "--strict", "-d", str(tmp_path)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        timeout=600,
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-6000:]
    assert (tmp_path / "reference" / "config" / "index.html").is_file()
    # formulas are MathML, which a browser draws with no script: none is left as LaTeX
    assert (
        '<math xmlns="http://www.w3.org/1998/Math/MathML"' in (tmp_path / "index.html").read_text()
    )
    assert not [p for p in tmp_path.rglob("*.html") if 'class="arithmatex"' in p.read_text()]


@pytest.mark.e2e
@pytest.mark.slow
@pytest.mark.parametrize("page", PAGES, ids=[str(p.relative_to(ROOT)) for p in PAGES])
def test_page_blocks_run(page, tmp_path, capsys):
    if not any(b.lang in ("bash", "python", "pycon") for b in blocks(page)):
        pytest.skip("no code to run")
    skipped = run_page(page, tmp_path)
    with capsys.disabled():
        for reason in skipped:
            print(f"\n  not run: {reason}")
