"""Interruption: Ctrl-C and SIGTERM end a command with one line and exit 130/143, no traceback; an output
set appears whole or not at all; temporary files go; sweep workers die with their parent; a closed
output pipe ends quietly (torchdoct.runtime.interrupt, torchdoct.files.output_set)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from _scenes import DIFFUSION_SWEEP_TOML

from torchdoct.cli import main
from torchdoct.files import atomic_write, output_set
from torchdoct.runtime.interrupt import deferred, entry_point, note


def _kill_self(sig=signal.SIGTERM):
    os.kill(os.getpid(), sig)
    time.sleep(2)  # the handler raises in the main thread before this returns
    raise AssertionError("the signal did not interrupt")


def _files(d: Path) -> set[str]:
    return {str(p.relative_to(d)) for p in d.rglob("*")}


def _one_line(err: str, code_name: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith(f"interrupted ({code_name})") and "Traceback" not in err
    return lines[0]


# ----------------------------------------------------------------------------------------------------------
# the entry-point wrapper and deferral
# ----------------------------------------------------------------------------------------------------------
def test_sigterm_and_ctrl_c_give_one_line_and_the_signal_exit_code(capsys):
    before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)

    @entry_point
    def cmd(sig):
        note(kept="3 finished cells in the cache c", resume="rerun to resume", key="cache")
        _kill_self(sig)

    assert cmd(signal.SIGTERM) == 143
    line = _one_line(capsys.readouterr().err, "SIGTERM")
    assert line == "interrupted (SIGTERM): kept 3 finished cells in the cache c; rerun to resume"
    assert cmd(signal.SIGINT) == 130
    _one_line(capsys.readouterr().err, "Ctrl-C")
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before  # handlers restored

    @entry_point
    def plain():
        _kill_self()

    assert plain() == 143
    line = _one_line(capsys.readouterr().err, "SIGTERM")  # the notes of the earlier run are not repeated
    assert line == (
        "interrupted (SIGTERM): no output was written (outputs appear only when complete); rerun the same command"
    )


def test_deferred_holds_the_signal_until_the_block_ends(capsys):
    done = []

    @entry_point
    def cmd():
        with deferred():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.2)
            done.append("block finished")
        done.append("after the block")  # never reached: the held signal is raised when the block ends
        return 0

    assert cmd() == 143
    assert done == ["block finished"]
    _one_line(capsys.readouterr().err, "SIGTERM")


# ----------------------------------------------------------------------------------------------------------
# output sets
# ----------------------------------------------------------------------------------------------------------
def _write(stage, path: Path, text: str) -> None:
    atomic_write(stage(path), lambda tmp: Path(tmp).write_text(text))


def test_output_set_appears_whole_or_not_at_all(tmp_path):
    a, b, c = tmp_path / "a.csv", tmp_path / "b.json", tmp_path / "c.png"
    with pytest.raises(RuntimeError, match="boom"):
        with output_set([a, b, c], force=False) as stage:
            _write(stage, a, "1")
            raise RuntimeError("boom")
    assert _files(tmp_path) == set()  # nothing, not even the staging folder
    with output_set([a, b, c], force=False) as stage:
        _write(stage, a, "1")
        _write(stage, b, "2")
        _write(stage, c, "3")
        assert not a.exists()  # nothing under the final names before the end
    assert _files(tmp_path) == {"a.csv", "b.json", "c.png"}
    with pytest.raises(ValueError, match="exist.*--force"):
        with output_set([a, b, c], force=False):
            pass
    # --force: this run writes a and b only; the earlier run's c does not stay beside them
    with output_set([a, b, c], force=True) as stage:
        _write(stage, a, "10")
        _write(stage, b, "20")
    assert _files(tmp_path) == {"a.csv", "b.json"} and a.read_text() == "10"


def test_output_set_removes_the_temporary_files_a_killed_run_left(tmp_path):
    a = tmp_path / "a.csv"
    stale = [tmp_path / ".a.csv.k3j2h1.tmp.csv", tmp_path / ".a.csv.stage.tmp.x8y7"]
    stale[0].write_text("partial")
    stale[1].mkdir()
    (stale[1] / "a.csv").write_text("partial")
    other = tmp_path / ".other.csv.k3j2h1.tmp.csv"  # not of this set: kept
    other.write_text("x")
    with output_set([a], force=True) as stage:
        _write(stage, a, "1")
    assert _files(tmp_path) == {"a.csv", other.name}


def _sleeper() -> subprocess.Popen:
    """Another running Python process (started: its command line is in place)."""
    proc = subprocess.Popen(
        [sys.executable, "-c", "import time; print(flush=True); time.sleep(60)"], stdout=subprocess.PIPE
    )
    proc.stdout.readline()
    proc.stdout.close()
    return proc


@pytest.mark.parametrize("temporary", [".a.csv.stage.{pid}.tmp.x8y7", ".a.csv.{pid}.k3j2h1.tmp.csv"])
def test_a_set_another_running_process_is_writing_is_a_write_conflict_naming_it(tmp_path, temporary):
    from torchdoct.files import WriteConflictError

    a = tmp_path / "a.csv"
    other = _sleeper()
    try:
        live = tmp_path / temporary.format(pid=other.pid)
        live.mkdir() if "stage" in temporary else live.write_text("being written")
        with pytest.raises(
            WriteConflictError,
            match=rf"write conflict: process {other.pid} \(.*python.*\) is "
            r"writing .*a\.csv now.*another --out",
        ):
            with output_set([a], force=True) as stage:
                _write(stage, a, "1")
        assert live.exists() and not a.exists()  # the other writer's files are left alone; nothing written
    finally:
        other.kill()
        other.wait()
    with output_set([a], force=True) as stage:  # it has ended: its leftovers are stale and go
        _write(stage, a, "1")
    assert _files(tmp_path) == {"a.csv"}


def test_a_writer_that_starts_during_the_set_stops_both_sets_landing(tmp_path):
    from torchdoct.files import WriteConflictError

    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    other = _sleeper()
    try:
        with pytest.raises(WriteConflictError, match=f"process {other.pid}"):
            with output_set([a, b], force=True) as stage:
                _write(stage, a, "1")
                (tmp_path / f".b.csv.stage.{other.pid}.tmp.q1w2").mkdir()  # the other run begins its set
                _write(stage, b, "2")
    finally:
        other.kill()
        other.wait()
    assert not a.exists() and not b.exists()


def test_a_sweep_losing_a_write_conflict_exits_1_naming_the_other_writer(tmp_path, capsys):
    scene = tmp_path / "sweep.toml"
    scene.write_text(DIFFUSION_SWEEP_TOML.format(trials=8))
    out = tmp_path / "out"
    out.mkdir()
    other = _sleeper()
    try:
        (out / f".results.csv.stage.{other.pid}.tmp.abcd").mkdir()
        code = main(["sweep", str(scene), "--out", str(out), "--no-progress", "--workers", "1", "--no-cache"])
    finally:
        other.kill()
        other.wait()
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith("error: --out: write conflict: process") and str(other.pid) in err[0]
    assert "does not exist" not in err[0] and not (out / "results.csv").exists()


def test_a_signal_during_the_renames_is_held_until_the_set_is_whole(tmp_path, monkeypatch, capsys):
    files = [tmp_path / f"f{i}.txt" for i in range(4)]
    real_replace = os.replace
    calls = []

    def replace(src, dst):
        calls.append(dst)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)  # arrives between the first and the second rename
            time.sleep(0.1)
        real_replace(src, dst)

    @entry_point
    def cmd():
        with output_set(files, force=False) as stage:
            for f in files:
                _write(stage, f, f.name)
            monkeypatch.setattr(os, "replace", replace)
        return 0

    assert cmd() == 143
    monkeypatch.undo()
    assert _files(tmp_path) == {f.name for f in files}  # all four, then the interruption
    line = _one_line(capsys.readouterr().err, "SIGTERM")
    assert f"kept the complete outputs {files[0]} and 3 more" in line


# ----------------------------------------------------------------------------------------------------------
# commands
# ----------------------------------------------------------------------------------------------------------
def test_render_interrupted_while_writing_leaves_nothing_and_reruns_without_force(tmp_path, monkeypatch, capsys):
    import torchdoct.image.render as render_module

    real = render_module.save_preview

    def preview(*args, **kwargs):  # the data file and its sidecar are written; SIGTERM comes now
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.5)
        return real(*args, **kwargs)

    monkeypatch.setattr(render_module, "save_preview", preview)
    out = tmp_path / "r.npz"
    argv = ["render", "spheroid", "--grid", "8x8", "--pitch-um", "2", "--out", str(out), "--no-progress"]
    assert main(argv) == 143
    _one_line(capsys.readouterr().err, "SIGTERM")
    assert _files(tmp_path) == set()  # no npz and json without their png, no temporary files
    monkeypatch.undo()
    assert main(argv) == 0  # the rerun needs no --force
    assert _files(tmp_path) == {"r.npz", "r.json", "r.png"}


@pytest.mark.slow  # longer than the default suite allows one test (CONTRIBUTING.md, markers)
def test_study_interrupted_while_writing_keeps_its_cache_and_says_so(tmp_path, monkeypatch, capsys):
    from _studies import write_tiny_study

    import torchdoct.study.run as run_module

    path = write_tiny_study(tmp_path, trials=16)
    real = run_module.claims_report

    def report(*args, **kwargs):  # tables and figures are written; SIGTERM comes now
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.5)
        return real(*args, **kwargs)

    monkeypatch.setattr(run_module, "claims_report", report)
    out = tmp_path / "out"
    argv = ["study", str(path), "--out", str(out), "--workers", "1", "--no-progress"]
    assert main(argv) == 143
    line = _one_line(capsys.readouterr().err, "SIGTERM")
    assert f"in the cache {out / 'cache'}" in line and "rerun the same command" in line
    assert {p.name for p in out.iterdir()} == {"cache"}  # 9 of 16 files before: now none
    assert not list(out.glob("cache/.*"))
    monkeypatch.undo()
    assert main(argv) == 0
    assert "36 from the cache" in capsys.readouterr().out


# ----------------------------------------------------------------------------------------------------------
# processes: Ctrl-C on a running command, worker processes, closed pipes
# ----------------------------------------------------------------------------------------------------------
def _env() -> dict[str, str]:
    return {**os.environ, "OMP_NUM_THREADS": "1"}


def _children(pid: int) -> list[int]:
    out = subprocess.run(["ps", "-o", "pid=", "--ppid", str(pid)], capture_output=True, text=True).stdout
    return [int(x) for x in out.split()]


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as fh:
            return fh.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.fixture
def sweeps():
    """Start sweeps with ``sweeps(tmp_path, trials, workers)``; any still running when the test ends (a
    failed one) is killed with its workers, so it cannot disturb the next tests."""
    started: list[subprocess.Popen] = []

    def start(tmp_path, trials: int, workers: int) -> tuple[subprocess.Popen, Path]:
        proc, out = _sweep(tmp_path, trials, workers)
        started.append(proc)
        return proc, out

    yield start
    for proc in started:
        if proc.poll() is None:
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        proc.communicate()


def _sweep(tmp_path, trials: int, workers: int) -> tuple[subprocess.Popen, Path]:
    scene = tmp_path / "sweep.toml"
    scene.write_text(DIFFUSION_SWEEP_TOML.format(trials=trials), encoding="utf-8")
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "torchdoct.cli",
            "sweep",
            str(scene),
            "--out",
            str(out),
            "--workers",
            str(workers),
            "--no-progress",
        ],
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    deadline = time.time() + 300
    while time.time() < deadline and not list(out.glob("cache/[!.]*.npz")):
        time.sleep(0.05)
    return proc, out


@pytest.mark.slow  # a few seconds: in the slow suite, so that the default suite stays under about five minutes
def test_ctrl_c_on_a_running_sweep(tmp_path, sweeps):
    proc, out = sweeps(tmp_path, trials=2048, workers=1)
    os.killpg(proc.pid, signal.SIGINT)  # a terminal sends Ctrl-C to the whole process group
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    line = _one_line(err, "Ctrl-C")
    assert "of the 16 cells to compute in the cache" in line and "resume" in line
    assert {p.name for p in out.iterdir()} == {"cache"}
    assert not list((out / "cache").glob(".*"))  # no temporary files


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_sweep_workers_die_with_their_parent(tmp_path, sig, sweeps):
    """16 cells of 65,536 trials: worker processes (torchdoct.study.sweep._PROCESS_WORK)."""
    proc, out = sweeps(tmp_path, trials=65536, workers=2)
    kids = _children(proc.pid)
    assert kids, "the sweep runs in worker processes"
    if sig == signal.SIGINT:
        os.killpg(proc.pid, sig)
    else:
        os.kill(proc.pid, sig)
    _, err = proc.communicate(timeout=120)
    deadline = time.time() + 10
    while time.time() < deadline and any(_alive(k) for k in kids):
        time.sleep(0.1)
    assert not any(_alive(k) for k in kids)  # before the fix the workers outlived the command
    if sig != signal.SIGKILL:
        assert proc.returncode == 128 + sig
        _one_line(err, "SIGTERM" if sig == signal.SIGTERM else "Ctrl-C")


HALF_A_RESULT = """
import multiprocessing, struct, time
from concurrent.futures import ProcessPoolExecutor
from torchdoct.study.cells import _stop_workers

with ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn")) as pool:
    running = pool.submit(time.sleep, 60)
    queued = pool.submit(time.sleep, 60)
    manager = pool._executor_manager_thread
    # what a worker stopped in the middle of sending a 1 MB result leaves in the pipe: the length and 10 bytes
    pool._result_queue._writer._send(struct.pack("!i", 1_000_000) + bytes(10))
    time.sleep(0.5)  # the manager thread now waits for the other 999,990 bytes
    _stop_workers(pool)
    print("manager thread alive:", manager.is_alive())
"""


def test_a_worker_stopped_while_it_sends_a_result_does_not_hang_the_command():
    """The CI hang of a SIGTERM'd sweep (torchdoct.study.cells._stop_workers): the pool's manager thread
    waited forever for the rest of half a message, and the interpreter joins it at exit."""
    proc = subprocess.run(
        [sys.executable, "-c", HALF_A_RESULT], capture_output=True, text=True, timeout=120, env=_env()
    )
    assert proc.returncode == 0 and proc.stdout.strip() == "manager thread alive: False", proc.stderr
    assert proc.stderr == ""  # no traceback from the manager thread (e.g. a cancelled future set broken)


@pytest.mark.parametrize("cmd", [["torchdoct.cli", "scenes"], ["classifier.cli", "--help"]])
def test_a_closed_output_pipe_ends_quietly(cmd):
    if cmd[0] == "classifier.cli":  # doct-classify --help
        code = "import sys; from classifier.cli import classify_main; sys.exit(classify_main(['--help']))"
        argv = [sys.executable, "-c", code]
    else:
        argv = [sys.executable, "-m", *cmd]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=_env())
    proc.stdout.close()  # the reader went away before the first line (`| head -0`)
    proc.stdout = None
    err = proc.communicate(timeout=120)[1].decode()
    assert proc.returncode in (0, 141) and err == ""
