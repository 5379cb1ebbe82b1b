"""Signals sent to `wl` at the moments the other tests miss (stop 63): while the packages are imported (and an
import swallows the KeyboardInterrupt), between the parse and the command, in a command's late import, as a worker
process is started, as an atomic write sets up its temporary file, during a codegen build; and the folders an
interrupted command created.

Each signal here is a real one, sent by the process to itself (or one of its threads) at a chosen point (a patched
step), so the moment is exact where a timed signal from outside hit it in 1 run in 3 to 1 in 150."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

import wl.cli

ROOT = Path(__file__).resolve().parents[1]


def _swallowed_then(error: BaseException, sig: int = signal.SIGINT) -> None:
    """A real ``sig`` to this process, whose KeyboardInterrupt C code swallows and turns into ``error`` with no chain
    (numpy's import: "PyCapsule_Import could not import module ..."; the measured traceback, exit 1)."""
    try:
        os.kill(os.getpid(), sig)
        time.sleep(5)  # (the handler raises here)
    except KeyboardInterrupt:
        pass
    raise error


def _numpy_like() -> None:
    _swallowed_then(ImportError('PyCapsule_Import could not import module "datetime"'))


def test_ctrl_c_that_an_import_at_start_up_turned_into_an_import_error_exits_130(monkeypatch, capsys):
    """Ctrl-C 90-200 ms into `wl evaluate` (numpy's import inside the parser's build) was numpy's ImportError
    traceback, exit 1, in 3 of 30 signals: no KeyboardInterrupt in its chain, and no flag set (no handler yet)."""
    monkeypatch.setattr(wl.cli, "build_parser", _numpy_like)
    assert wl.cli.main(["params"]) == 130
    assert capsys.readouterr().err.strip() == "wl: interrupted"


def test_an_import_error_that_is_no_interrupt_is_still_raised(monkeypatch):
    def broken() -> None:
        raise ImportError("a broken install")

    monkeypatch.setattr(wl.cli, "build_parser", broken)
    with pytest.raises(ImportError, match="a broken install"):
        wl.cli.main(["params"])


def test_ctrl_c_inside_a_commands_late_import_exits_130(monkeypatch, capsys):
    """The commands import their packages late (torch, CasADi): the same ImportError there was a traceback, as
    `_run_command` took no ImportError."""
    monkeypatch.setattr(wl.cli, "_params_cmd", lambda args: _numpy_like())
    assert wl.cli.main(["params"]) == 130
    assert capsys.readouterr().err.strip() == "wl: interrupted"


def _wl_with(patch: str, argv: list[str], env: dict[str, str] | None = None) -> subprocess.CompletedProcess:
    """`wl argv` as the program (sys.argv, so that it exits as `wl` does), with ``patch`` applied to wl.cli first."""
    code = textwrap.dedent(f"""
        import os, signal, sys, time
        import wl.cli
        {patch}
        sys.argv = ["wl", *{argv!r}]
        sys.exit(wl.cli.main())
    """)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=ROOT,
                          env={**os.environ, **(env or {})})


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["SIGINT", "SIGTERM"])
def test_a_signal_between_the_parse_and_the_command_is_no_traceback(sig, code):
    """The environment's check ran after the parse and before the command's handler: Ctrl-C there was a
    KeyboardInterrupt's traceback (its imports take 10-25 ms with $WL_CODEGEN or $WL_NLP_CACHE_SIZE set)."""
    patch = (f"wl.cli._check_environment = lambda: (os.kill(os.getpid(), {int(sig)}), time.sleep(5))")
    r = _wl_with(patch, ["params", "--json"])
    assert r.returncode == code, r.stderr
    assert r.stderr.strip() == "wl: interrupted" and "Traceback" not in r.stderr
    assert r.stdout == ""


@pytest.mark.parametrize("sig,code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)], ids=["SIGINT", "SIGTERM"])
def test_a_signal_while_the_parser_imports_exits_cleanly(sig, code):
    """SIGTERM while the packages were imported killed `wl` outright (no cleanup, no message); as the rest of the
    command it is now the interrupt, 143."""
    patch = (f"def build():\n    os.kill(os.getpid(), {int(sig)})\n    time.sleep(5)\n"
             "wl.cli.build_parser = build")
    r = _wl_with(textwrap.indent(patch, " " * 8).strip(), ["params"])
    assert r.returncode == code, r.stderr
    assert r.stderr.strip() == "wl: interrupted"


def test_an_interrupt_removes_the_wl_cache_dir_it_created_and_keeps_one_it_found(tmp_path, monkeypatch, capsys):
    """An interrupted `wl evaluate` left the $WL_CACHE_DIR folder it created (empty) behind; `--cache` was removed.
    A folder that was there before is kept, empty or not."""
    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(wl.cli, "_params_cmd", interrupted)
    new = tmp_path / "new" / "cache"
    monkeypatch.setenv("WL_CACHE_DIR", str(new))
    assert wl.cli.main(["params"]) == 130
    assert not (tmp_path / "new").exists()
    found = tmp_path / "found"
    found.mkdir()
    monkeypatch.setenv("WL_CACHE_DIR", str(found))
    assert wl.cli.main(["params"]) == 130
    assert found.is_dir()
    monkeypatch.setenv("WL_CACHE_DIR", str(new))  # a command that ends well keeps it
    monkeypatch.setattr(wl.cli, "_params_cmd", lambda args: 0)
    assert wl.cli.main(["params"]) == 0
    assert new.is_dir()
    capsys.readouterr()


def test_an_interrupted_training_leaves_no_empty_log_dir_or_run_folder(tmp_path, monkeypatch, capsys):
    """Ctrl-C 1-7 s into `wl train` (before its config.json) left the new --log-dir, and from ~5 s the run's own
    folder, empty: `runs/` and `runs/a/`."""
    import agents.ppo

    def interrupted(cfg, resume=False, command=None, callbacks=None):
        cfg.run_dir.mkdir(parents=True, exist_ok=True)
        raise KeyboardInterrupt

    monkeypatch.setattr(agents.ppo, "train", interrupted)
    log_dir = tmp_path / "new" / "runs"
    argv = ["train", "--log-dir", str(log_dir), "--run-name", "a", "--total-timesteps", "4096", "--num-envs", "8",
            "--no-progress-bar", "--cache", str(tmp_path / "cache")]
    assert wl.cli.main(argv) == 130
    assert "the same command starts it again" in capsys.readouterr().err
    assert not (tmp_path / "new").exists() and not (tmp_path / "cache").exists()
    # a run folder that holds something (or was there before) stays, and so does its log dir
    (log_dir / "a").mkdir(parents=True)
    (log_dir / "a" / "config.json").write_text("{}")
    assert wl.cli.main(argv) == 130
    assert (log_dir / "a" / "config.json").is_file()


@pytest.mark.parametrize("moment", ["umask", "chmod"])
def test_ctrl_c_as_an_atomic_write_sets_up_its_temporary_file_leaves_none(tmp_path, monkeypatch, moment):
    """The temporary file was made before the `try` that removes it: Ctrl-C while its mode was set (the umask is
    read line by line from /proc/self/status) left `.x.json.<random>.tmp` beside the result."""
    from wl_env import atomic_io

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    if moment == "umask":
        monkeypatch.setattr(atomic_io, "current_umask", interrupted)
    else:
        monkeypatch.setattr(atomic_io.os, "chmod", interrupted)
    (tmp_path / "x.json").write_text("old\n")
    with pytest.raises(KeyboardInterrupt):
        atomic_io.write_json_atomic(tmp_path / "x.json", {"new": 1})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.json"]
    assert (tmp_path / "x.json").read_text() == "old\n"


def test_an_interrupted_seeds_run_leaves_no_empty_run_folders(tmp_path, monkeypatch, capsys):
    """Ctrl-C 35 s into `wl train --seeds 1 2 --ray` (the Ray tasks had made their run folders, not yet their
    config.json) left `runs/ppo_service_s1/` and `runs/ppo_service_s2/` empty. The same without Ray."""
    import agents.seeds

    def interrupted(cfg_dict, command=None):
        cfg = agents.seeds.PPOConfig.from_dict(cfg_dict)
        cfg.run_dir.mkdir(parents=True, exist_ok=True)
        raise KeyboardInterrupt

    monkeypatch.setattr(agents.seeds, "train_one", interrupted)
    log_dir = tmp_path / "runs"
    argv = ["train", "--log-dir", str(log_dir), "--seeds", "1", "2", "--total-timesteps", "4096", "--num-envs", "8",
            "--no-progress-bar"]
    assert wl.cli.main(argv) == 130
    assert not log_dir.exists(), sorted(p.name for p in log_dir.iterdir())
    (log_dir / "ppo_service_s1").mkdir(parents=True)  # a run folder that was there before stays
    assert wl.cli.main(argv) == 130
    assert (log_dir / "ppo_service_s1").is_dir() and not (log_dir / "ppo_service_s2").exists()
    capsys.readouterr()


def test_an_interrupted_training_hints_a_resume_only_where_there_is_a_run_to_resume(tmp_path, monkeypatch, capsys):
    """Ctrl-C 5-7 s into `wl train` (before its config.json) printed "continue with: wl train --run-name a --log-dir
    ... --resume", and that command failed: "wl: error: nothing to resume: .../a/config.json does not exist", exit 2."""
    import agents.ppo

    def interrupted(cfg, resume=False, command=None, callbacks=None):
        if record:
            cfg.run_dir.mkdir(parents=True, exist_ok=True)
            (cfg.run_dir / "config.json").write_text("{}")
        raise KeyboardInterrupt

    monkeypatch.setattr(agents.ppo, "train", interrupted)
    argv = ["train", "--log-dir", str(tmp_path / "runs"), "--run-name", "a", "--total-timesteps", "4096",
            "--num-envs", "8", "--no-progress-bar"]
    record = False
    assert wl.cli.main(argv) == 130
    err = capsys.readouterr().err
    assert "--resume" not in err and "the same command starts it again" in err
    record = True
    assert wl.cli.main(argv) == 130
    assert f"--run-name a --log-dir {tmp_path / 'runs'} --resume" in capsys.readouterr().err


# the end of each script below: one worker whose job takes 3 s, and how long the interrupt took to end it
_RUN_A_WORKER = """
t0 = time.monotonic()
try:
    print("ran on:", workers.run_in_workers({"a": ("time:sleep", (3.0,))}), flush=True)
except KeyboardInterrupt:
    print("interrupted after %.1f s" % (time.monotonic() - t0), flush=True)
"""


def _run_interrupted(script: str) -> subprocess.CompletedProcess:
    """``script`` run in a process of its own; it must end by the interrupt within 2.5 s, before its worker's job."""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert "interrupted after" in r.stdout, r.stdout + r.stderr
    assert float(r.stdout.split("after ")[1].split()[0]) < 2.5
    return r


_LOST_CTRL_C = """
import os, signal, sys, time
import multiprocessing.util as util
from mpc import interrupt, workers

spawn = util.spawnv_passfds
calls = []

def spawn_then_ctrl_c(*args, **kwargs):
    calls.append(args[1][-1] if args[1] else "")
    if len(calls) > 1:  # a worker's spawn (the first process started is multiprocessing's resource tracker)
        os.kill(os.getpid(), signal.SIGINT)
    return spawn(*args, **kwargs)

util.spawnv_passfds = spawn_then_ctrl_c
interrupt.install()
""" + _RUN_A_WORKER


def test_ctrl_c_as_the_first_worker_starts_is_never_lost():
    """Ctrl-C (the process group's, as a terminal sends it) 0.83 s into `wl pareto --braking both`: 1 run in 10 hung
    for good (120 s, both workers solving, the parent waiting). multiprocessing's resource tracker, started by the
    first worker's start, unblocks SIGINT inside `_sigint_held`, where SIGINT is ignored: a Ctrl-C then was dropped.
    Here the signal comes as the first worker is spawned, after the tracker started."""
    r = _run_interrupted(_LOST_CTRL_C)
    assert "Traceback" not in r.stderr, r.stderr


_HELD_CTRL_C = """
import os, signal, sys
import multiprocessing
from mpc import workers

recv, send = multiprocessing.Pipe(duplex=False)
pid = os.fork()
if pid == 0:  # a worker as spawned: SIGINT ignored and blocked, and a Ctrl-C that came meanwhile pending
    recv.close()
    signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.kill(os.getpid(), signal.SIGINT)
    try:
        workers._child(send, os.getppid(), 20, "math:sqrt", (4.0,))
    finally:
        os._exit(3)
send.close()
try:
    kind, value, tb = recv.recv()
    print("reported:", kind, type(value).__name__, tb, flush=True)
except EOFError:
    print("no report", flush=True)
print("exit", os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1]), flush=True)
"""


def test_a_ctrl_c_held_while_a_worker_starts_is_reported_not_a_traceback():
    """Ctrl-C to the process group 0.9-1.3 s into `wl pareto --braking both` printed a worker's traceback ("Process
    wl-worker-tc: Traceback ... KeyboardInterrupt", 9 runs of 14): the SIGINT held since its spawn was raised where the
    worker unblocked it, outside the try that reports an interrupt to the parent."""
    r = subprocess.run([sys.executable, "-c", _HELD_CTRL_C], capture_output=True, text=True, timeout=60, cwd=ROOT)
    assert "reported: error KeyboardInterrupt None" in r.stdout, r.stdout + r.stderr
    assert "exit 1" in r.stdout and "Traceback" not in r.stderr, r.stdout + r.stderr


def _gone(pid: int, within: float = 2.0) -> bool:
    deadline = time.monotonic() + within
    while True:
        try:
            state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        except (FileNotFoundError, ProcessLookupError):
            return True
        if state in ("Z", "X") or time.monotonic() > deadline:
            return state in ("Z", "X")
        time.sleep(0.05)


def test_an_interrupted_codegen_build_kills_what_the_compiler_started(monkeypatch, tmp_path):
    """Ctrl-C 1-3.5 s into `wl mpc`'s first build of compiled NLP functions took 3.7-5.6 s to exit: `cc` was killed,
    but the `cc1` it runs held its output pipes, and the build waited for them to finish compiling. A compiler here
    that starts a child of its own, as `cc` does."""
    import casadi as ca

    from mpc.controller import codegen

    fake = tmp_path / "drivercc"
    pids = tmp_path / "pids"
    pids.mkdir()
    fake.write_text("#!/bin/sh\n[ \"$1\" = --version ] && { echo drivercc 1.0; exit 0; }\n"
                    f"sleep 12 &\necho $! > {pids}/$!\nwait\n")
    fake.chmod(0o755)
    monkeypatch.setenv("CC", str(fake))
    x, p = ca.SX.sym("x", 3), ca.SX.sym("p", 2)
    origin = ca.Function("s63_f", [x, p], [ca.sin(x[0]) * p[0] + x[1] * x[2] / p[1]])
    group = {"f": origin, "grad": ca.Function("s63_grad", [x, p], [ca.gradient(origin(x, p), x)])}
    timer = threading.Timer(1.0, signal.pthread_kill, (threading.main_thread().ident, signal.SIGINT))
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    codegen.set_mode("on")
    try:
        timer.start()
        t0 = time.monotonic()
        with pytest.raises(KeyboardInterrupt):
            codegen.compiled([group], [origin], cache=tmp_path)
        took = time.monotonic() - t0
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
        codegen.set_mode(None)
    assert took < 5.0
    started = [int(f.name) for f in pids.iterdir()]
    assert started, "the fake compiler never ran"
    for pid in started:  # (the compiler's own child: killed too; a zombie until whoever adopted it reaps it)
        assert _gone(pid), pid
    assert [f.name for f in (tmp_path / "codegen").iterdir()] == [".build.lock"]


def _swallowing(step):
    """``step`` after a real SIGINT whose KeyboardInterrupt C code swallowed whole (numpy's scalar types are
    registered with `abc` from its extension's init: a KeyboardInterrupt raised there is dropped), as an import."""
    def patched(*args, **kwargs):
        try:
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)
        except KeyboardInterrupt:
            pass
        return step(*args, **kwargs)
    return patched


@pytest.mark.parametrize("where", ["build_parser", "_check_environment"])
def test_a_ctrl_c_that_an_import_swallowed_is_still_the_interrupt(monkeypatch, capsys, where):
    """SIGINT to `wl pareto --braking both` 0.6 s in (its imports): 2 runs in ~150 hung, the parent waiting for the
    workers' whole fronts. The KeyboardInterrupt was raised inside `abc.register` during a C extension's import and
    dropped there; the flag it set was cleared when the command's handler was installed."""
    monkeypatch.setattr(wl.cli, where, _swallowing(getattr(wl.cli, where)))
    assert wl.cli.main(["params", "--json"]) == 130
    out, err = capsys.readouterr()
    assert out == "" and err.strip() == "wl: interrupted"


_SWALLOWED_BEFORE_THE_WORKERS = """
import os, signal, sys, time
from mpc import interrupt, workers

interrupt.install()
try:
    os.kill(os.getpid(), signal.SIGINT)
    time.sleep(5)
except KeyboardInterrupt:
    pass  # (swallowed, as inside an import)
""" + _RUN_A_WORKER


def test_workers_are_not_waited_for_after_a_swallowed_ctrl_c():
    _run_interrupted(_SWALLOWED_BEFORE_THE_WORKERS)


_CTRL_C_TO_ANOTHER_THREAD = """
import os, signal, sys, threading, time
import multiprocessing.util as util
from mpc import interrupt, workers

other = threading.Thread(target=time.sleep, args=(30,), daemon=True)  # (as numpy's BLAS threads: SIGINT unblocked)
other.start()
spawn = util.spawnv_passfds

def spawn_then_ctrl_c(*args, **kwargs):
    if "spawn_main" in " ".join(map(str, args[1])):  # a worker's spawn
        signal.pthread_kill(other.ident, signal.SIGINT)  # (the kernel's choice for a process's signal, made here)
        time.sleep(0.1)
    return spawn(*args, **kwargs)

util.spawnv_passfds = spawn_then_ctrl_c
interrupt.install()
""" + _RUN_A_WORKER


def test_a_ctrl_c_that_another_thread_receives_as_a_worker_starts_is_never_lost():
    """SIGINT to `wl pareto --braking both` 0.6-0.8 s in: ~1 run in 150 hung, the parent waiting for the workers'
    whole fronts, its interrupt flag unset. While a worker was spawned SIGINT was ignored (SIG_IGN) and blocked in the
    main thread only: the kernel gave the signal to another thread (numpy's BLAS threads), and it was dropped there."""
    r = _run_interrupted(_CTRL_C_TO_ANOTHER_THREAD)
    assert "Traceback" not in r.stderr, r.stderr
