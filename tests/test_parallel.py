"""Networks trained over worker processes (supramodal/parallel.py, supramodal.mlp.train_networks; issue
38 item 1): the same model for any number of jobs, progress told in the order of one job, failures
and the work threshold."""

from __future__ import annotations

import json
import math
import multiprocessing
import os

import numpy as np
import pytest

from supramodal import mlp
from supramodal.banks import whisker_bank
from supramodal.calibration import DEFAULT_CALIBRATION_FOLDS
from supramodal.errors import InputError
from supramodal.model import TextureModel
from supramodal.parallel import WorkerLost, map_in_processes

CLASSES = ("a", "b", "c")


def _windows(n_per_class: int = 40, seed: int = 0):
    """Three overlapping classes of 20-channel Af windows, in 4 recordings of each."""
    rng = np.random.default_rng(seed)
    y = np.repeat(np.arange(3), n_per_class)
    values = rng.normal(size=(len(y), 1, 20)) + 0.8 * np.eye(3)[y].repeat(7, axis=1)[:, None, :20]
    groups = np.array([f"{c}{k}" for c in range(3) for k in np.arange(n_per_class) * 4 // n_per_class])
    return values, y, groups


def _train(jobs: int, **kwargs):
    values, y, groups = _windows()
    epochs, folds = [], []
    model = TextureModel.train(values, y, CLASSES, whisker_bank(), ("Af",), 500, epochs=60, seed=3, groups=groups,
                               progress=lambda e, mse: epochs.append((e, mse)), calibration_progress=folds.append,
                               jobs=jobs, **kwargs)
    return model, epochs, folds


@pytest.fixture
def always_parallel(monkeypatch):
    """Workers for any work, so that a small training takes the path of a large one."""
    monkeypatch.setattr(mlp, "PARALLEL_MIN_WORK", 0.0)


def test_map_keeps_the_order_and_tells_each_call_once():
    told = []
    got = map_in_processes(math.factorial, [5, 0, 3, 7], jobs=2, done=lambda i, r: told.append((i, r)))
    assert got == [120, 1, 6, 5040]
    assert sorted(told) == [(0, 120), (1, 1), (2, 6), (3, 5040)]
    assert multiprocessing.active_children() == []            # the workers are gone


def test_map_with_one_job_runs_here_in_order():
    told = []
    assert map_in_processes(math.factorial, [4, 2], done=lambda i, r: told.append(i)) == [24, 2]
    assert told == [0, 1]


def test_a_failed_call_raises_in_the_caller_and_stops_the_workers():
    with pytest.raises(ValueError, match="negative"):
        map_in_processes(math.factorial, [3, -1, 4, 5], jobs=2)
    assert multiprocessing.active_children() == []


def test_a_worker_that_dies_is_said_at_once_not_waited_for():
    """A worker killed in the middle of a call (out of memory, a signal) ends the call with a clear error;
    a pool that quietly replaced it would wait for its result for ever."""
    with pytest.raises(WorkerLost, match=r"ended in the middle of its work \(exit code .*--jobs 1"):
        map_in_processes(os._exit, [3, 3, 3], jobs=2)
    assert multiprocessing.active_children() == []


def test_items_are_taken_as_workers_are_free_for_them():
    """A generator is consumed a few items at a time: no more than the workers and the one in hand."""
    taken = []

    def items():
        for k in range(8):
            taken.append(k)
            yield k

    seen_when_done = []
    got = map_in_processes(math.factorial, items(), jobs=2, done=lambda i, r: seen_when_done.append(len(taken)))
    assert got == [math.factorial(k) for k in range(8)]
    assert seen_when_done[0] <= 3                # when the first came back, at most 2 taken (+1 in hand)


@pytest.mark.parametrize("jobs", [0, -1, 1.5, "2", True])
def test_jobs_must_be_a_positive_integer(jobs):
    with pytest.raises(InputError, match="jobs must be an integer >= 1"):
        map_in_processes(math.factorial, [1], jobs=jobs)


def test_the_model_is_the_same_for_any_jobs(always_parallel):
    before = os.times()
    one, one_epochs, one_folds = _train(1)
    children = os.times().children_user - before.children_user
    two, two_epochs, two_folds = _train(2)
    assert os.times().children_user - before.children_user > children    # the workers trained them
    for p, q in zip(one.mlp.params(), two.mlp.params()):
        np.testing.assert_array_equal(p, q)
    assert json.dumps(one.calibration.to_dict(), sort_keys=True) == json.dumps(two.calibration.to_dict(),
                                                                               sort_keys=True)
    np.testing.assert_array_equal(one.out_of_fold.logits, two.out_of_fold.logits)
    np.testing.assert_array_equal(one.novelty_score(_windows(seed=9)[0]), two.novelty_score(_windows(seed=9)[0]))
    assert one.training == two.training
    # Progress: the folds' lines alike (in fold order with one job, as each is back from the workers);
    # of the last network, every epoch trained with one job; from them, the last epoch of the network kept
    # alone (where it stopped early, the epoch of its lowest held-out error: one of the epochs trained).
    assert sorted(two_folds) == sorted(one_folds) and len(one_folds) == DEFAULT_CALIBRATION_FOLDS
    assert [line.split(":")[0] for line in one_folds] == [f"calibration fold {f}/{DEFAULT_CALIBRATION_FOLDS}"
                                                          for f in range(1, DEFAULT_CALIBRATION_FOLDS + 1)]
    kept = one.training["network_epochs"][-1]
    assert len(one_epochs) == 60 and two_epochs == [one_epochs[kept - 1]]


def test_small_work_stays_in_this_process():
    before = os.times().children_user
    model, epochs, _ = _train(2)
    assert os.times().children_user == before              # below PARALLEL_MIN_WORK: no worker started
    assert len(epochs) == 60 and model.calibrated


def test_work_counts_every_multiply_add_of_the_training():
    task = mlp.NetworkTask(np.zeros((100, 20)), np.zeros(100, dtype=int), 8, hidden=10, epochs=50)
    assert task.work == 100 * 10 * (20 + 8) * 50
    assert mlp.NetworkTask(np.zeros((100, 20)), np.zeros(100, dtype=int), 8, epochs=50).work == 100 * 20 * 28 * 50


INTERRUPTED = """
import signal, sys, time
from supramodal.parallel import WorkerLost, map_in_processes

if __name__ == "__main__":
    # As at a terminal: a test worker of pytest-xdist ignores Ctrl-C, and a child inherits that.
    signal.signal(signal.SIGINT, signal.default_int_handler)
    print("mapping", flush=True)
    try:
        map_in_processes(time.sleep, [60, 60, 60], jobs=2)
    except KeyboardInterrupt:
        print("interrupted", flush=True)
        sys.exit(3)
"""


def test_ctrl_c_stops_the_workers_at_once(tmp_path):
    """Ctrl-C at a terminal (SIGINT to the whole process group) while the workers sleep for a minute: the
    call ends at once, the caller says so, and no process of the group is left."""
    import signal
    import subprocess
    import sys
    import time

    script = tmp_path / "interrupted.py"
    script.write_text(INTERRUPTED)
    proc = subprocess.Popen([sys.executable, str(script)], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, start_new_session=True)
    try:
        assert proc.stdout is not None and proc.stdout.readline() == "mapping\n"
        time.sleep(3.0)                         # the workers started (or starting: a Ctrl-C then stops them too)
        t0 = time.monotonic()
        os.killpg(proc.pid, signal.SIGINT)
        out, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 3, err
    assert out == "interrupted\n" and time.monotonic() - t0 < 60          # not the workers' minute
    deadline = time.monotonic() + 10
    while True:                                  # every worker gone with its caller
        try:
            os.killpg(proc.pid, 0)
        except ProcessLookupError:
            break
        assert time.monotonic() < deadline, "a worker outlived its caller"
        time.sleep(0.1)
