"""``cathtrack compile``: the kernels compiled ahead, several jobs at a time, stage after stage.

The jobs here stand in for the compilations: each runs in a spawned process, as the real
ones do, and leaves a file behind. Two jobs of a stage each wait for the other to have
started, so they pass only when they run at the same time; a job of the next stage checks
that both have ended.
"""

from __future__ import annotations

import _thread
import os
import threading
import time
from pathlib import Path

import pytest

import replay.commands.compile as compile_command
import replay.compile_ahead as compile_ahead
from replay import parallel
from replay.cli import main
from replay.compile_ahead import STAGES, compile_all

_FOLDER = "CATHTRACK_TEST_COMPILE_FOLDER"
_WAIT_S = 60.0  # only a failure waits this long


def _mark(name: str) -> None:
    (Path(os.environ[_FOLDER]) / name).touch()


def _wait_for(name: str) -> None:
    path = Path(os.environ[_FOLDER]) / name
    deadline = time.monotonic() + _WAIT_S
    while not path.exists():
        if time.monotonic() > deadline:
            raise TimeoutError(f"{name} never came: the jobs did not run at the same time")
        time.sleep(0.01)


def _first() -> None:
    _mark("first started")
    _wait_for("second started")
    _mark("first ended")


def _second() -> None:
    _mark("second started")
    _wait_for("first started")
    _mark("second ended")


def _after() -> None:
    folder = Path(os.environ[_FOLDER])
    if not ((folder / "first ended").exists() and (folder / "second ended").exists()):
        raise RuntimeError("the second stage started before the first had ended")
    _mark("after ended")


def _long() -> None:
    (Path(os.environ[_FOLDER]) / "long pid").write_text(str(os.getpid()))
    time.sleep(_WAIT_S)


def _long_too() -> None:
    (Path(os.environ[_FOLDER]) / "long too pid").write_text(str(os.getpid()))
    time.sleep(_WAIT_S)


def _fails_once_long_runs() -> None:
    _wait_for("long pid")
    _fails()


def _here() -> None:
    (Path(os.environ[_FOLDER]) / "here pid").write_text(str(os.getpid()))


def _here_too() -> None:
    (Path(os.environ[_FOLDER]) / "here too pid").write_text(str(os.getpid()))


def _after_here() -> None:
    if not (Path(os.environ[_FOLDER]) / "here pid").exists():
        raise RuntimeError("the second stage ran before the first")
    _mark("after ended")


def _fails() -> None:
    raise ValueError("cannot determine the numba type of <object>")


PARALLEL = ((("first", _first), ("second", _second)), (("after", _after),))


@pytest.fixture
def folder(tmp_path, monkeypatch) -> Path:
    monkeypatch.setenv(_FOLDER, str(tmp_path))  # the spawned processes inherit it
    return tmp_path


def test_the_jobs_of_a_stage_run_at_once_and_the_next_stage_after_them(folder):
    lines: list[str] = []
    took = compile_all(2, report=lines.append, stages=PARALLEL)
    assert (folder / "after ended").exists()
    assert took > 0
    assert len(lines) == 3
    assert sorted(line.split(":")[0].strip() for line in lines[:2]) == ["first", "second"]
    assert lines[2].startswith("  after: ") and lines[2].endswith("(3 of 3)")
    assert [line[-8:] for line in lines[:2]] == ["(1 of 3)", "(2 of 3)"]


def _gone(pid_file: Path) -> bool:
    """Whether the process that wrote ``pid_file`` has ended and been reaped."""
    try:
        os.kill(int(pid_file.read_text()), 0)
    except ProcessLookupError:
        return True
    return False


def test_a_job_that_fails_is_named_its_stage_ended_and_the_next_not_run(folder):
    stages = ((("the model", _fails_once_long_runs), ("long", _long)), (("after", _after),))
    started = time.monotonic()
    with pytest.raises(RuntimeError, match="compiling the model failed: cannot determine"):
        compile_all(2, report=lambda line: None, stages=stages)
    assert time.monotonic() - started < _WAIT_S  # the other job was not waited for
    assert _gone(folder / "long pid")
    assert not (folder / "after ended").exists()


ONE_AFTER_ANOTHER = ((("here", _here),), (("after", _after_here),))


def test_one_job_at_a_time_runs_the_jobs_in_this_process_in_order(folder):
    lines: list[str] = []
    compile_all(1, report=lines.append, stages=ONE_AFTER_ANOTHER)
    assert int((folder / "here pid").read_text()) == os.getpid()
    assert (folder / "after ended").exists()
    assert [line.split(":")[0].strip() for line in lines] == ["here", "after"]


def test_without_worker_processes_the_jobs_run_here_and_a_line_says_so(folder, monkeypatch):
    def no_semaphores(*args, **kwargs):
        raise OSError("[Errno 38] Function not implemented")

    monkeypatch.setattr(parallel, "ProcessPoolExecutor", no_semaphores)
    lines: list[str] = []
    stages = ((("here", _here), ("here too", _here_too)), (("after", _after_here),))
    compile_all(2, report=lines.append, stages=stages)
    assert int((folder / "here pid").read_text()) == os.getpid()
    assert int((folder / "here too pid").read_text()) == os.getpid()
    assert lines[0] == (
        "no worker processes here ([Errno 38] Function not implemented): the jobs run one"
        " after the other in this process"
    )
    assert [line.split(":")[0].strip() for line in lines[1:]] == ["here", "here too", "after"]
    assert (folder / "after ended").exists()


def test_a_job_that_fails_in_this_process_is_named(folder):
    with pytest.raises(RuntimeError, match="compiling grid failed: cannot determine"):
        compile_all(1, report=lambda line: None, stages=((("grid", _fails),),))


def test_ctrl_c_ends_the_job_processes_at_once(folder):
    def interrupt() -> None:  # Ctrl-C once both jobs run
        _wait_for("long pid")
        _wait_for("long too pid")
        _thread.interrupt_main()

    threading.Thread(target=interrupt, daemon=True).start()
    started = time.monotonic()
    with pytest.raises(KeyboardInterrupt):
        compile_all(2, report=lambda line: None, stages=((("long", _long), ("too", _long_too)),))
    assert time.monotonic() - started < _WAIT_S  # the jobs were not waited for
    assert _gone(folder / "long pid") and _gone(folder / "long too pid")
    assert os.getpid() != int((folder / "long pid").read_text())  # they ran in workers


def test_the_command_reports_each_job_and_a_failure_in_one_line(folder, monkeypatch, capsys):
    def with_stages(stages):
        return lambda jobs, report: compile_all(jobs, report, stages)

    monkeypatch.setattr(compile_command, "compile_all", with_stages(PARALLEL))
    assert main(["compile", "--jobs", "2"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "cathtrack compile: the numba kernels, 2 at a time (cached: only loaded)"
    assert out[-1].startswith("cathtrack compile: done in ") and out[-1].endswith(" s")
    assert len(out) == 5

    monkeypatch.setattr(compile_command, "compile_all", with_stages(((("grid", _fails),),)))
    assert main(["compile"]) == 1
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "cathtrack compile: error: compiling grid failed: cannot determine the numba type of"
        " <object>"
    ]


def test_a_number_of_jobs_below_one_is_refused(capsys):
    assert main(["compile", "--jobs", "0"]) == 2
    assert capsys.readouterr().err.strip() == (
        "cathtrack compile: error: --jobs must be at least 1, got 0"
    )


def test_every_stage_has_jobs_with_labels_and_the_rules_come_before_their_callers():
    labels = [label for stage in STAGES for label, _ in stage]
    assert len(labels) == len(set(labels)) and all(labels)
    first = {label for label, _ in STAGES[0]}
    later = {label for stage in STAGES[1:] for label, _ in stage}
    # The filters' step and runs call the rules: compiled with them, they would be twice.
    assert "the filters' rules" in first
    assert any("the filters' step" in label for label in later)


def test_a_set_up_still_running_after_its_time_says_the_kernels_may_be_compiling_once():
    said = threading.Event()
    lines: list[str] = []

    def report(line: str) -> None:
        lines.append(line)
        said.set()

    notice = compile_ahead.SlowSetUpNotice(report, after_s=0.0)
    with notice.during():
        assert said.wait(_WAIT_S)  # the block outlasts its time: the notice comes
    said.clear()
    with notice.during():  # a second slow block of the same set-up (the demo has two)
        time.sleep(0.01)
    assert lines == [compile_ahead.SLOW_SET_UP]  # once
    assert "cathtrack compile" in lines[0] and "make" in lines[0]


def test_a_set_up_that_ends_in_time_says_nothing_and_stops_its_timer(monkeypatch):
    timers: list[threading.Timer] = []

    class Timer(threading.Timer):
        def __init__(self, *args, **kwargs) -> None:
            super().__init__(*args, **kwargs)
            timers.append(self)

    monkeypatch.setattr(compile_ahead.threading, "Timer", Timer)
    lines: list[str] = []
    with compile_ahead.SlowSetUpNotice(lines.append, after_s=_WAIT_S).during():
        set_up = "done"  # a set-up that takes no time
    assert set_up == "done"
    timers[0].join(_WAIT_S)  # a cancelled timer ends at once; one left running would not
    assert not timers[0].is_alive() and lines == []
