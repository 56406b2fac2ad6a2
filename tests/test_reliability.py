"""Nothing lost, nothing silently wrong (issue 34): verified checkpoints and selected
policies, readers that leave checkpoints/ alone, one writer per run, the run's state, and
memory checked before anything is written."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys

import numpy as np
import pytest
from test_evaluate import fake_run_dir
from tiny import tiny

from ttd3_jax.cli import train
from ttd3_jax.run import checkpoint as ckpt
from ttd3_jax.run import memory, rundir, status
from ttd3_jax.run import spec as sp
from ttd3_jax.run.loop import finished_note
from ttd3_jax.sim import custom_tracks as ct
from ttd3_jax.sim.env import mixture_num_segments, num_validation_tracks

GIB = 2**30


def two_checkpoints(tmp_path) -> str:
    """A run directory with checkpoints 2 and 3 (3 = 2's state), each with its digest."""
    run_dir = fake_run_dir(tmp_path / "run")
    state = rundir.load_train_state(run_dir).state
    ckpt.save(ckpt.manager(run_dir), 3, state)
    return run_dir


def data_files(run_dir: str, epoch: int) -> list[str]:
    root = os.path.join(run_dir, "checkpoints", str(epoch))
    files = [os.path.join(d, f) for d, _, fs in os.walk(root) for f in fs]
    return sorted(files, key=os.path.getsize, reverse=True)


def test_random_bytes_in_the_newest_checkpoint_fall_back_to_the_one_before(tmp_path):
    run_dir = two_checkpoints(tmp_path)
    assert set(ckpt.digests(run_dir)) == {2, 3}
    path = data_files(run_dir, 3)[0]  # the largest data file
    size = os.path.getsize(path)
    with open(path, "r+b") as fh:
        fh.seek(size // 2)
        fh.write(np.random.default_rng(0).bytes(min(4096, size - size // 2)))
    loaded = rundir.load_train_state(run_dir)
    assert loaded.epoch == 2 and [e for e, _ in loaded.skipped] == [3]


def test_a_checkpoint_that_loads_but_differs_from_its_digest_is_skipped(tmp_path):
    run_dir = two_checkpoints(tmp_path)
    record = ckpt.digests(run_dir)
    record[3] = "0" * 32  # as if the files had changed without failing to decode
    with open(os.path.join(run_dir, ckpt.DIGESTS), "w") as fh:
        json.dump({str(k): v for k, v in record.items()}, fh)
    loaded = rundir.load_train_state(run_dir)
    assert loaded.epoch == 2 and "do not match the digest" in loaded.skipped[0][1]


def test_readers_leave_a_trainers_unfinished_save_alone(tmp_path):
    run_dir = fake_run_dir(tmp_path / "run")
    tmp = os.path.join(run_dir, "checkpoints", "3.orbax-checkpoint-tmp-1234")
    os.makedirs(tmp)
    before = sorted(os.listdir(os.path.join(run_dir, "checkpoints")))
    assert rundir.load_train_state(run_dir).epoch == 2
    assert os.path.isdir(tmp) and sorted(os.listdir(os.path.join(run_dir, "checkpoints"))) == before


def test_a_damaged_selected_policy_is_detected(tmp_path):
    like = {"actor": {"w": np.zeros((3, 2), np.float32)}, "obs_stats": None}
    policy = {"actor": {"w": np.arange(6, dtype=np.float32).reshape(3, 2)}, "obs_stats": None}
    ckpt.save_policy(str(tmp_path), 7, 4, 1.5, policy)
    np.testing.assert_array_equal(
        ckpt.load_policy(str(tmp_path), 7, like)["actor"]["w"], policy["actor"]["w"]
    )
    path = tmp_path / "best" / "seed7.msgpack"
    data = bytearray(path.read_bytes())
    data[-8:] = np.random.default_rng(1).bytes(8)  # the last weights: still valid msgpack
    path.write_bytes(bytes(data))
    with pytest.raises(ckpt.CorruptCheckpoint, match="does not match the digest in best/best.json"):
        ckpt.load_policy(str(tmp_path), 7, like)
    with pytest.raises(ValueError, match="no longer kept, so it cannot be rebuilt"):
        rundir.selected_policy(str(tmp_path), 7, 0, like, 4)


def dead_pid() -> int:
    p = subprocess.Popen(["true"])
    p.wait()
    return p.pid


def test_one_writer_per_run_and_a_stale_lock_is_taken_over(tmp_path):
    run_dir = str(tmp_path)
    assert status.acquire(run_dir) is None
    with pytest.raises(
        status.RunLocked, match=rf"being trained by pid {os.getpid()} on .*one writer per run"
    ):
        status.acquire(run_dir)
    status.release(run_dir)
    assert status.holder(run_dir) is None
    lock = {"pid": dead_pid(), "host": status.socket.gethostname(), "since": "then"}
    (tmp_path / status.LOCK).write_text(json.dumps(lock))
    note = status.acquire(run_dir)
    assert note == f"took over the lock of pid {lock['pid']} on {lock['host']}, which is no longer running"
    assert status.holder(run_dir)["pid"] == os.getpid()
    status.release(run_dir)


def test_the_state_says_failed_with_the_reason_and_running_turns_interrupted(tmp_path):
    run_dir = str(tmp_path)
    with pytest.raises(ZeroDivisionError), status.writing(run_dir, log=lambda *a: None):
        assert status.state(run_dir)["state"] == "running"
        1 / 0  # noqa: B018
    assert status.state(run_dir)["reason"].startswith("ZeroDivisionError")
    assert status.holder(run_dir) is None
    status.mark(run_dir, "running")
    assert status.state(run_dir)["state"] == "interrupted"  # nobody holds the lock: it was killed


def test_find_run_skips_failed_runs_and_says_so(tmp_path):
    good = rundir.new_run_dir(str(tmp_path), tiny())
    status.mark(good, "finished")
    bad = rundir.new_run_dir(str(tmp_path), tiny(seed=1))
    status.mark(bad, "failed", reason="MemoryError: out of memory")
    path, note = rundir.find_run(str(tmp_path))
    assert path == good and f"skipped {os.path.basename(bad)} (failed: MemoryError" in note


def test_resume_of_a_finished_run_does_nothing(tmp_path):
    run_dir = rundir.new_run_dir(str(tmp_path), tiny())
    assert finished_note(run_dir, tiny()) is None
    status.mark(run_dir, "finished")
    assert "finished all 2 epochs (eval.json); nothing to resume" in finished_note(run_dir, tiny())


@pytest.mark.parametrize(
    "argv, field",
    [
        (["--hidden", "65536", "65536"], "--hidden 65536 65536"),
        (["--task.episode-steps", "2000000000"], "--task.episode-steps 2000000000"),
        (["--updates-per-step", "1000000000"], "--updates-per-step 1000000000"),
        (["--num-seeds", "20000"], "--num-seeds 20000"),  # the rollout grows with it: blamed, not the horizon
        (
            ["--num-envs", "3000000", "--buffer-size", "3000000", "--total-transitions", "400000000"],
            "--num-envs 3000000",
        ),
        (
            ["--num-envs", "100000000", "--model-horizon", "1", "--total-transitions", "400000000"],
            "--num-envs 100000000",
        ),  # not --task.episode-steps, which was never set
    ],
)
def test_each_memory_case_is_refused_with_the_figure_and_the_field_set_largest(argv, field):
    _, spec = train.parse(["--total-transitions", "20000", "--epochs", "2", *argv])
    trainer = sp.trainer_for(spec)
    with pytest.raises(ValueError) as e:
        memory.check(spec, trainer.env.obs_size, trainer.env.action_size, free=16 * GIB)
    assert re.search(
        rf"the run needs about [\d.e+]+ GiB of memory, .*\({re.escape(field)}\), but only 16 GiB",
        str(e.value),
    )


def test_presets_fit_and_a_refused_run_writes_nothing(tmp_path, capsys):
    for name in ("fast", "fast_dpg", "paper"):
        s = sp.preset(name)
        t = sp.trainer_for(s)
        assert memory.check(s, t.env.obs_size, t.env.action_size, free=16 * GIB) < 4 * GIB
    out = tmp_path / "runs"
    code = train.main(["--total-transitions", "20000", "--epochs", "2", "--hidden", "65536", "65536",
                       "--out", str(out), "--compile-cache", "none"])  # fmt: skip
    assert code == 2 and "--hidden 65536 65536" in capsys.readouterr().err
    assert not out.exists()


def test_a_full_disk_or_no_memory_ends_in_one_line_with_what_to_do():
    full = OSError(28, "No space left on device")
    full.run_dir = "runs/r1"
    assert train.failure_message(full) == (
        "the disk is full; free space, then continue with python -m ttd3_jax.train --resume runs/r1"
    )
    wrapped = ValueError("orbax: save failed")
    wrapped.__cause__ = OSError(28, "No space left on device")
    assert train.failure_message(wrapped).startswith("the disk is full")
    assert train.failure_message(RuntimeError("RESOURCE_EXHAUSTED: Out of memory")).startswith(
        "out of memory"
    )
    assert train.failure_message(RuntimeError("something else")) is None


QUIET_PROBE = """
import threading
from ttd3_jax.cli import train
train._quiet_background_failures()
class Closed:  # an exception in __del__ reaches sys.unraisablehook, as tensorstore's threads' do
    def __init__(self, text):
        self.text = text
    def __del__(self):
        raise RuntimeError(self.text)
Closed("Event loop is closed")
def fail(text):
    raise RuntimeError(text)
thread = threading.Thread(target=fail, args=("Event loop is closed",))
thread.start(); thread.join()
Closed("another failure")
"""


def test_a_failing_background_save_prints_no_closed_event_loop_traceback():
    """orbax/tensorstore threads report 'Event loop is closed' through sys.unraisablehook and
    threading.excepthook while a save fails on a full disk; only those are kept off stderr."""
    probe = subprocess.run([sys.executable, "-c", QUIET_PROBE], capture_output=True, text=True, timeout=120)
    assert probe.returncode == 0, probe.stderr
    assert "Event loop is closed" not in probe.stderr
    assert "RuntimeError: another failure" in probe.stderr  # other errors still print


HALF_CLOSED_LOOP = """
import asyncio, gc, sys
from ttd3_jax.cli import train
if sys.argv[1] == "quiet":
    train._quiet_background_failures()
loop = asyncio.new_event_loop()
loop._ssock.close()  # where a KeyboardInterrupt inside loop.close() leaves it: socket closed, loop open
del loop
gc.collect()
"""


@pytest.mark.parametrize("mode", ["quiet", "plain"])
def test_a_second_ctrl_c_inside_an_asyncio_loop_close_prints_no_finalizer_traceback(mode):
    """CI once caught a second SIGTERM landing inside orbax's ``loop.close()``: the loop's
    ``__del__`` then raised ``Invalid file descriptor: -1`` after the one-line stop message.
    The train CLI keeps that finalizer's noise off stderr; without it, Python prints it."""
    probe = subprocess.run(
        [sys.executable, "-c", HALF_CLOSED_LOOP, mode], capture_output=True, text=True, timeout=120
    )
    assert probe.returncode == 0, probe.stderr
    printed = "Invalid file descriptor" in probe.stderr
    assert printed == (mode == "plain"), probe.stderr


def small_state(seed: int) -> dict:
    rng = np.random.default_rng(seed)
    return {"buffer": rng.standard_normal((256, 8)).astype(np.float32), "step": np.array([seed], np.int32)}


def saved_twice(run_dir: str, asynchronous: bool = False) -> None:
    m = ckpt.manager(run_dir, asynchronous=asynchronous)
    ckpt.save(m, 1, small_state(1), wait=not asynchronous)
    ckpt.save(m, 2, small_state(2), wait=not asynchronous)
    ckpt.close(m)


def test_a_changed_byte_in_any_file_of_the_newest_checkpoint_is_detected(tmp_path):
    """Metadata, commit markers and unused bytes included: the file hashes, not the contents."""
    run_dir = str(tmp_path)
    saved_twice(run_dir, asynchronous=True)
    files = ckpt.file_digests(run_dir)
    assert set(files) == {1, 2} and files[2] == ckpt.hash_files(os.path.join(run_dir, "checkpoints", "2"))
    for rel in files[2]:
        path = os.path.join(run_dir, "checkpoints", "2", rel)
        data = bytearray(open(path, "rb").read())
        data[len(data) // 2] ^= 0x01
        open(path, "wb").write(bytes(data))
        epoch, got, skipped = ckpt.restore_newest(run_dir, small_state(0))
        assert epoch == 1 and np.array_equal(got["buffer"], small_state(1)["buffer"]), rel
        assert skipped == [
            (2, f"CorruptCheckpoint: its file {rel} changed since it was saved ({ckpt.FILES})")
        ]
        data[len(data) // 2] ^= 0x01
        open(path, "wb").write(bytes(data))
    assert ckpt.restore_newest(run_dir, small_state(0))[0] == 2  # all restored: 2 loads again


def test_a_checkpoint_killed_before_its_file_hashes_loads_on_its_content_digest_with_a_note(tmp_path):
    run_dir = str(tmp_path)
    saved_twice(run_dir)
    record = ckpt.file_digests(run_dir)
    del record[2]  # as if killed between orbax's finalisation and the hashes being written
    (tmp_path / ckpt.FILES).write_text(json.dumps({str(k): v for k, v in record.items()}))
    notes = []
    epoch, got, skipped = ckpt.restore_newest(run_dir, small_state(0), note=notes.append)
    assert (epoch, skipped) == (2, []) and np.array_equal(got["buffer"], small_state(2)["buffer"])
    assert notes == [f"checkpoint 2 has no file hashes ({ckpt.FILES}; the run stopped before they were "
                     "written); its contents match their digest, so it is loaded"]  # fmt: skip
    contents = ckpt.digests(run_dir)
    contents[2] = "0" * 32  # and its contents differ: it falls back as before
    (tmp_path / ckpt.DIGESTS).write_text(json.dumps({str(k): v for k, v in contents.items()}))
    assert ckpt.restore_newest(run_dir, small_state(0), note=notes.append)[0] == 1 and len(notes) == 1


def test_a_junk_file_hash_record_is_named_as_the_cause(tmp_path):
    run_dir = str(tmp_path)
    saved_twice(run_dir)
    (tmp_path / ckpt.FILES).write_text("{not json")
    notes = []
    assert ckpt.restore_newest(run_dir, small_state(0), note=notes.append)[0] == 2
    assert notes == [f"checkpoint 2 has no file hashes ({ckpt.FILES} is damaged); its contents match their "
                     "digest, so it is loaded"]  # fmt: skip


def test_saving_again_an_epoch_that_was_deleted_drops_its_old_file_hashes(tmp_path, monkeypatch):
    run_dir = str(tmp_path)
    saved_twice(run_dir)
    m = ckpt.manager(run_dir)
    m.delete(2)  # what resume does with a checkpoint that does not load
    monkeypatch.setattr(ckpt._Recorder, "run", lambda self: None)  # killed before the new hashes
    ckpt.save(m, 2, small_state(5))
    ckpt.close(m)
    assert set(ckpt.file_digests(run_dir)) == {1}  # not the deleted checkpoint's hashes
    epoch, got, _ = ckpt.restore_newest(run_dir, small_state(0), note=lambda message: None)
    assert epoch == 2 and np.array_equal(got["buffer"], small_state(5)["buffer"])


def test_resume_past_a_damaged_newest_checkpoint_says_so_once_and_prints_no_traceback(tmp_path):
    """The damage that made orbax's threads print 'Event loop is closed' (an OCDBT manifest that
    no longer decodes) is now caught by the file hashes before orbax reads anything."""
    run_dir = two_checkpoints(tmp_path)
    with open(os.path.join(run_dir, "metrics.csv"), "w") as fh:  # the epochs' rows (the results need them)
        fh.write("epoch,seed,env_steps,eval_return\n1,0,16,0.0\n2,0,32,0.0\n")
    manifest = os.path.join(run_dir, "checkpoints", "3", "default", "manifest.ocdbt")
    data = bytearray(open(manifest, "rb").read())
    data[4] ^= 0xFF
    open(manifest, "wb").write(bytes(data))
    rel = os.path.relpath(manifest, os.path.join(run_dir, "checkpoints", "3"))
    res = subprocess.run([sys.executable, "-m", "ttd3_jax.train", "--resume", run_dir],
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert res.returncode == 0, res.stdout + res.stderr
    assert (f"skipped checkpoint 3, which does not load (CorruptCheckpoint: its file {rel} changed since it "
            f"was saved ({ckpt.FILES})); it is deleted") in res.stdout  # fmt: skip
    assert f"resumed {run_dir} at epoch 2/2" in res.stdout
    for noise in ("Traceback", "Event loop is closed", "ERROR", "Exception"):
        assert noise not in res.stderr, res.stderr


def test_remove_deletes_a_run_killed_before_its_first_checkpoint_and_nothing_else(tmp_path, capsys):
    unstarted = rundir.new_run_dir(str(tmp_path), tiny())
    status.mark(unstarted, "running")  # killed during compile or warm-up: no checkpoint
    os.makedirs(os.path.join(unstarted, "checkpoints", "0.orbax-checkpoint-tmp-7"))
    assert train.main(["--remove", unstarted]) == 0
    assert capsys.readouterr().out == f"removed {unstarted} (it stopped before its first checkpoint)\n"
    assert not os.path.exists(unstarted)
    trained = two_checkpoints(tmp_path)
    assert train.main(["--remove", trained]) == 2
    err = capsys.readouterr().err
    assert f"{trained} holds checkpoint(s) [2, 3]" in err and f"--resume {trained}" in err
    assert os.path.isdir(os.path.join(trained, "checkpoints", "3"))
    live = rundir.new_run_dir(str(tmp_path), tiny(seed=1))
    status.acquire(live)  # a live process (this one) trains it
    assert train.main(["--remove", live]) == 2 and "one writer per run" in capsys.readouterr().err
    assert os.path.isdir(live)
    status.release(live)
    assert train.main(["--remove", live, "--epochs", "3"]) == 2
    assert "--remove deletes a run and takes nothing else; remove --epochs 3" in capsys.readouterr().err
    assert (
        train.main(["--remove", str(tmp_path / "nope")]) == 2
        and "not a ttd3_jax run" in capsys.readouterr().err
    )


def test_a_long_user_training_track_counts_in_the_memory_check_and_is_named(tmp_path):
    path = str(tmp_path / "long.csv")  # 60 s: every env's track table grows to its 60,000+ rows
    ct.to_csv(ct.step((0.0, 0.0, 0.3), 60.0, name="long"), path)
    _, spec = train.parse(["--total-transitions", "20000", "--epochs", "2", "--buffer-size", "20000",
                           "--task.tracks.train-tracks", path])  # fmt: skip
    trainer = sp.trainer_for(spec)
    rows = trainer.env.env.num_segments
    assert rows > 60_000 > mixture_num_segments(spec.task)
    tables = spec.train.num_envs + 1 + num_validation_tracks(spec.task) + 2  # envs, the user's, val, test
    big = memory.track_bytes(spec, rows)
    assert big == spec.num_seeds * tables * rows * memory.TRACK_ROW_BYTES
    assert big > 40 * memory.track_bytes(spec)  # the mixture's tables alone: what was counted before
    named = rf"the track tables \(--task.tracks.train-tracks {re.escape(path)}\)"
    with pytest.raises(ValueError, match=named):
        memory.check(spec, trainer.env.obs_size, trainer.env.action_size, free=big, track_rows=rows)


def test_best_keeps_the_lowest_validation_policy_or_with_selection_last_the_newest(tmp_path):
    from types import SimpleNamespace

    from ttd3_jax.td3.config import TrainConfig

    def epochs(selection: str) -> dict:
        run_dir = str(tmp_path / selection)
        train = TrainConfig(selection=selection, normalize_obs=False)
        spec = SimpleNamespace(seed=3, num_seeds=2, train=train)
        for epoch, vals in enumerate([(5.0, 2.0), (1.0, 4.0), (3.0, 3.0)], start=1):
            ts = SimpleNamespace(actor={"w": np.full((2, 1), epoch, np.float32)}, obs_stats=None)
            rundir.select_best(run_dir, spec, epoch, {"val_tracking_error": np.asarray(vals)}, ts)
        return {s: r["epoch"] for s, r in ckpt.best_record(run_dir).items()}

    assert epochs("validation") == {3: 2, 4: 1}  # the lowest validation error per seed
    assert epochs("last") == {3: 3, 4: 3}
    with pytest.raises(ValueError, match="selection"):
        TrainConfig(selection="best")
