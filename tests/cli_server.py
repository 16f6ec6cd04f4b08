"""The package's console scripts run in forks of one process that has already imported them.

A console script is ``sys.exit(<entry point>())`` after ``import torchrl_stages.cli``, and that
import (torch, tensordict, torchrl) is most of a short command's time: about 4 of a smoke
run's 6-8 seconds. :class:`CLIServer` starts one server process per test worker that imports
the package once; each command then runs in a fork of it, as the console script would: its own
``argv``, working directory, environment (``PYTHONPATH`` entries put on ``sys.path``), stdin
from ``/dev/null``, stdout and stderr to files, the entry point's exit status, and the
interpreter's exit handlers (a failed sweep writes its summary in one). Commands started
together run at the same time, each in its own fork, as background processes would.

Only plain commands go this way (``[VAR=value ...] <console script> args``, no operators or
redirections; bash itself expands ``~`` and ``$HOME`` in their words): :func:`plain_command`
says which; the others run in ``bash`` as before.
"""

from __future__ import annotations

import atexit
import functools
import json
import os
import re
import runpy
import select
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
import traceback
from importlib.metadata import entry_points
from pathlib import Path

ASSIGNMENT = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*=")
SHELL = re.compile(r"[$`~\\]")  # expansions and escapes: bash expands the words
POLL_S = 0.02  # how often the server looks for ended commands
#: one torch (OpenMP, MKL) thread in the server and its forks, as in the test processes: two
#: pytest workers share the machine's cores, and a process of two threads beside a busy one
#: runs 3-4x slower than one of one thread
ONE_THREAD = {"OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


@functools.cache
def console_scripts() -> dict[str, str]:
    """The package's console scripts: name -> ``module:function``."""
    return {
        ep.name: ep.value
        for ep in entry_points(group="console_scripts")
        if ep.value.startswith("torchrl_stages.")
    }


def plain_command(
    command: str, env: dict[str, str] | None = None, cwd: Path | None = None
) -> tuple[dict[str, str], list[str]] | None:
    """``(assignments, argv)`` of a command a fork can run like ``bash -c`` would: optional
    ``VAR=value`` words, then one of the package's console scripts and its arguments, with no
    operator or redirection. Its words are as the shell quotes them; where it has expansions
    (``~``, ``$HOME``) or escapes, as bash expands them in ``env`` and ``cwd`` (given ``env``
    only: ``None`` without it). ``None`` otherwise."""
    lexer = shlex.shlex(command, posix=True, punctuation_chars=True)
    lexer.whitespace_split = True
    try:
        words = list(lexer)
    except ValueError:  # unbalanced quotes
        return None
    if any(w and set(w) <= set("();<>|&") for w in words):  # operators and redirections
        return None
    if SHELL.search(command):
        words = _expanded(command, env, cwd) if env is not None else None
        if words is None:
            return None
    assignments = {}
    while words and ASSIGNMENT.match(words[0]):
        name, value = words.pop(0).split("=", 1)
        assignments[name] = value
    if not words or words[0] not in console_scripts():
        return None
    return assignments, words


def _expanded(command: str, env: dict[str, str], cwd: Path | None) -> list[str] | None:
    """The words of ``command`` after bash's expansions, as ``bash -c`` would pass them (a
    leading ``VAR=value`` word included); ``None`` where bash refuses the command."""
    script = f"set -- {command}\nprintf '%s\\0' \"$@\""
    done = subprocess.run(["bash", "-c", script], env=env, cwd=cwd, capture_output=True)
    if done.returncode != 0 or done.stderr:
        return None
    return [w.decode() for w in done.stdout.split(b"\0")[:-1]]


class CLIServer:
    """A server process that has imported the package; each command runs in a fork of it.

    :meth:`start` sends a command and returns once it is forked (several may run at the same
    time, as background processes would; :meth:`pid` is the fork's process, which signals
    reach as they reach any); :meth:`wait` returns its result; :meth:`run` does both.
    """

    def __init__(self) -> None:
        self.scratch = Path(tempfile.mkdtemp(prefix="cli_server_"))  # the commands' outputs
        self.proc = subprocess.Popen(
            [sys.executable, str(Path(__file__).resolve())],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            bufsize=0,  # replies are read as they come (_read), never held in a buffer
            env={**os.environ, **ONE_THREAD},  # what the forks inherit: test workers share cores
        )
        self._jobs: dict[int, list[str]] = {}  # started and not yet waited for: job -> argv
        self._pids: dict[int, int] = {}  # job -> its fork's process id
        self._replies: dict[int, dict] = {}  # finished and not yet waited for
        self._pending = b""  # the start of a reply not yet whole
        self._next = 0

    def start(
        self,
        argv: list[str],
        cwd: Path,
        env: dict[str, str],
        timeout: float,
        file_size_limit: int | None = None,
    ) -> int:
        """Starts ``argv`` in a fork, in ``cwd`` with ``env``: a console script and its
        arguments, or a ``.py`` script and its arguments (run as ``python`` runs it). Returns
        the job to :meth:`wait` for; a command still running after ``timeout`` seconds is
        killed. ``file_size_limit``: no file it writes may grow past that many bytes."""
        job, self._next = self._next, self._next + 1
        request = {
            "job": job,
            "argv": argv,
            "cwd": str(cwd),
            "env": env,
            "timeout": timeout,
            "file_size_limit": file_size_limit,
            "stdout": str(self._output(job, "stdout")),
            "stderr": str(self._output(job, "stderr")),
        }
        self._send(request)
        self._jobs[job] = argv
        while job not in self._pids:
            self._read(block=True)
        return job

    def pid(self, job: int) -> int:
        """The process id of a started command's fork."""
        return self._pids[job]

    def finished(self, job: int) -> bool:
        """Whether a started command has ended (without waiting)."""
        self._read(block=False)
        return job in self._replies

    def wait(self, job: int) -> subprocess.CompletedProcess:
        """The result of a started command, as a subprocess's would be (once per job); one
        that ran past its timeout raises :class:`subprocess.TimeoutExpired`."""
        argv = self._jobs.pop(job)
        while job not in self._replies:
            self._read(block=True)
        reply = self._replies.pop(job)
        self._pids.pop(job, None)
        out, err = self._output(job, "stdout"), self._output(job, "stderr")
        stdout, stderr = out.read_text(), err.read_text()
        out.unlink()
        err.unlink()
        if reply["timed_out"]:
            raise subprocess.TimeoutExpired(argv, reply["timeout"], stdout, stderr)
        return subprocess.CompletedProcess(argv, reply["returncode"], stdout, stderr)

    def run(
        self, argv: list[str], cwd: Path, env: dict[str, str], timeout: float
    ) -> subprocess.CompletedProcess:
        """Runs ``argv`` to completion (:meth:`start`, then :meth:`wait`)."""
        return self.wait(self.start(argv, cwd, env, timeout))

    def kill(self, job: int) -> None:
        """Stops a started command that has not been waited for (its result is dropped)."""
        if job in self._jobs:
            self._send({"kill": job})
            self.wait(job)

    def _send(self, request: dict) -> None:
        self.proc.stdin.write((json.dumps(request) + "\n").encode())
        self.proc.stdin.flush()

    def _read(self, block: bool) -> None:
        """Takes in the server's replies that have come (waits for one if ``block``): a
        command's fork (``pid``) or its end (``returncode``)."""
        stream = self.proc.stdout.fileno()
        if not block and not select.select([stream], [], [], 0)[0]:
            return
        chunk = os.read(stream, 1 << 16)
        if not chunk:
            raise RuntimeError(f"the CLI server exited (status {self.proc.wait()})")
        *lines, self._pending = (self._pending + chunk).split(b"\n")
        for line in filter(bytes.strip, lines):
            reply = json.loads(line)
            if "pid" in reply:
                self._pids[reply["job"]] = reply["pid"]
            else:
                self._replies[reply["job"]] = reply

    def _output(self, job: int, stream: str) -> Path:
        return self.scratch / f"{job}.{stream}"

    def close(self) -> None:
        """Ends the server; commands still running are killed."""
        self.proc.stdin.close()  # the server's loop ends
        self.proc.wait(timeout=30)
        self.proc.stdout.close()
        shutil.rmtree(self.scratch, ignore_errors=True)


_SHARED: list[CLIServer] = []


def shared_server() -> CLIServer:
    """This test process's server, started on first use and closed when the process exits."""
    if not _SHARED or _SHARED[0].proc.poll() is not None:
        _SHARED[:] = [CLIServer()]
        atexit.register(_SHARED[0].close)
    return _SHARED[0]


# ------------------------------------------------------------------------------ the server
def _child(request: dict, scripts: dict[str, str]) -> None:
    """In the fork: becomes the command, then exits with its status (never returns)."""
    code = 1
    try:
        os.chdir(request["cwd"])
        os.environ.clear()
        os.environ.update(request["env"])
        paths = [p for p in request["env"].get("PYTHONPATH", "").split(os.pathsep) if p]
        sys.path[:0] = [os.path.abspath(p) for p in paths]
        os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
        flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
        os.dup2(os.open(request["stdout"], flags), 1)
        os.dup2(os.open(request["stderr"], flags), 2)
        if request.get("file_size_limit") is not None:  # past it, a write fails (EFBIG)
            import resource

            limit = int(request["file_size_limit"])
            resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))
        sys.argv = list(request["argv"])
        try:
            if sys.argv[0].endswith(".py"):  # python <script> args: the script as __main__
                sys.path.insert(0, os.path.dirname(os.path.abspath(sys.argv[0])))
                runpy.run_path(sys.argv[0], run_name="__main__")
                status = None
            else:  # sys.exit(<entry point>())
                module, function = scripts[sys.argv[0]].split(":")
                __import__(module)
                status = getattr(sys.modules[module], function)()
        except SystemExit as stop:
            status = stop.code
        if status is None:
            code = 0
        elif isinstance(status, int):
            code = status
        else:  # sys.exit("message"): printed, status 1
            print(status, file=sys.stderr)
            code = 1
    except BaseException:  # noqa: BLE001 - the command's traceback, as the interpreter prints it
        traceback.print_exc()
        code = 1
    finally:
        atexit._run_exitfuncs()  # as the interpreter does at exit (a sweep's summary is written so)
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except Exception:  # noqa: BLE001
                pass
        os._exit(code)


def _import_what_a_run_imports() -> None:
    """The imports a training run makes after the console script's own, made once here rather
    than in every fork (about 1 of a smoke run's 7 seconds): the package's task modules,
    Hydra's core plugins, pandas, which tensordict imports, when installed, on the first
    random action (``TensorDict.from_any``), rliable's statistics, which every sweep,
    study and report summary imports (1-2 s: scipy, statsmodels, arch; no pyplot), and
    matplotlib's figure and Agg canvas, which every run's figures import (about 0.5 s)."""
    import importlib
    import importlib.util

    from hydra.core.plugins import Plugins

    importlib.import_module("torchrl_stages.envs")
    Plugins.instance()
    for module in (
        "pandas",
        "rliable.library",
        "matplotlib.figure",
        "matplotlib.backends.backend_agg",
    ):
        if importlib.util.find_spec(module.split(".")[0]) is not None:
            importlib.import_module(module)


def serve() -> None:
    """Reads one request per line from stdin, forks each, and writes one reply per line to
    stdout when it ends (in the order they end); at the end of stdin, kills what still runs."""
    if sys.path[0] == str(Path(__file__).resolve().parent):
        del sys.path[0]  # a console script does not see the tests' modules
    import torchrl_stages.cli  # noqa: F401 - what every fork inherits

    _import_what_a_run_imports()
    scripts = console_scripts()
    running: dict[int, tuple[dict, float]] = {}  # pid -> (request, deadline)
    requests, pending = sys.stdin.fileno(), b""
    while requests is not None or running:
        if requests is not None and select.select([requests], [], [], POLL_S)[0]:
            chunk = os.read(requests, 1 << 16)
            if not chunk:  # the client closed: nothing will read a reply
                requests = None
                for pid in running:
                    os.kill(pid, signal.SIGKILL)
            *lines, pending = (pending + chunk).split(b"\n")
            for line in filter(bytes.strip, lines):
                request = json.loads(line)
                if "kill" in request:  # a started command the client stops
                    for pid, (started, _) in running.items():
                        if started["job"] == request["kill"]:
                            os.kill(pid, signal.SIGKILL)
                    continue
                pid = os.fork()
                if pid == 0:
                    _child(request, scripts)
                running[pid] = (request, time.monotonic() + request["timeout"])
                sys.stdout.write(json.dumps({"job": request["job"], "pid": pid}) + "\n")
                sys.stdout.flush()
        elif requests is None:
            time.sleep(POLL_S)
        for pid, (request, deadline) in list(running.items()):
            done, status = os.waitpid(pid, os.WNOHANG)
            timed_out = not done and time.monotonic() > deadline
            if timed_out:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
            elif not done:
                continue
            del running[pid]
            if requests is not None:
                code = -signal.SIGKILL if timed_out else os.waitstatus_to_exitcode(status)
                reply = {"job": request["job"], "returncode": code, "timed_out": timed_out}
                sys.stdout.write(json.dumps({**reply, "timeout": request["timeout"]}) + "\n")
                sys.stdout.flush()


if __name__ == "__main__":
    serve()
