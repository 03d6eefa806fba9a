"""d2turb.io.writer: the background writer surfaces its errors, bounds its queue, phases its writes around
the computation and starts no compute threads; d2turb.io.jobs: the skeleton of the batch jobs over input files."""

import os
import time
from pathlib import Path

import pytest
import torch

from d2turb.errors import D2TurbError
from d2turb.io import BackgroundWriter, write_image, write_json


def test_background_writer_surfaces_errors_and_bounds_the_queue(tmp_path):
    import threading

    gate = threading.Event()
    done = []
    writer = BackgroundWriter(max_pending=2, threads=1)
    writer.submit(gate.wait)
    writer.submit(done.append, 1)
    writer.submit(done.append, 2)  # queue full now: the next submit would block until the gate opens
    gate.set()
    writer.submit(lambda: (_ for _ in ()).throw(D2TurbError("disk on fire")))
    writer.submit(done.append, 3)  # dropped or run: the error is reported either way
    with pytest.raises(D2TurbError, match="disk on fire"):
        for _ in range(100):
            writer.submit(done.append, 4)
            time.sleep(0.01)
        writer.close()
    assert done[:2] == [1, 2]
    with BackgroundWriter() as w:  # a clean run writes everything
        for i in range(5):
            w.submit(write_json, tmp_path / f"{i}.json", {"i": i})
    assert sorted(p.name for p in tmp_path.iterdir()) == [f"{i}.json" for i in range(5)]


def test_phased_writer_finishes_the_queued_writes_before_each_computation():
    import threading

    gate, done = threading.Event(), []

    def slow(i):
        gate.wait(30)
        done.append(i)

    from d2turb.device import usable_cores

    cores = usable_cores()
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(cores)
        with BackgroundWriter(compute_device="cuda", threads=1) as writer:  # a GPU computation: writes overlap it
            writer.submit(slow, 0)
            writer.before_compute()
            assert done == [] and not writer.phased
            gate.set()
        assert done == [0]
        gate.clear()
        with BackgroundWriter(compute_device="cpu", threads=2) as writer:  # every core computing: writes first
            assert writer.phased
            for i in range(1, 5):
                writer.submit(slow, i)
            threading.Timer(0.05, gate.set).start()
            writer.before_compute()
            assert sorted(done) == [0, 1, 2, 3, 4]
        if cores > 1:  # a core left free for the writer: overlap
            torch.set_num_threads(cores - 1)
            with BackgroundWriter(compute_device="cpu") as writer:
                assert not writer.phased
        torch.set_num_threads(cores)
        writer = BackgroundWriter(compute_device="cpu")
    finally:
        torch.set_num_threads(threads)
    writer.submit(lambda: (_ for _ in ()).throw(D2TurbError("disk on fire")))
    with pytest.raises(D2TurbError, match="disk on fire"):
        writer.before_compute()
    with pytest.raises(D2TurbError, match="disk on fire"):  # sticky: close reports it too
        writer.close()


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="counts threads in /proc")
def test_background_writes_start_no_compute_threads(tmp_path):
    """Writers convert tensors with numpy: a torch operator in a writer thread would start an OpenMP team of
    its own, and more compute threads than cores slow the main computation. The only new thread is the writer."""
    import threading

    from d2turb.data.layout import write_depth_png

    threads = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        image = torch.rand(3, 256, 256)
        image.clamp(0, 1)  # this thread's own team exists before counting
        before = set(os.listdir("/proc/self/task"))
        written = threading.Event()
        with BackgroundWriter(threads=1) as writer:
            writer.submit(write_image, tmp_path / "a.png", image)
            writer.submit(write_depth_png, tmp_path / "d.png", image[:1])
            writer.submit(written.set)
            assert written.wait(60)
            # threads started meanwhile (a thread of an earlier test, e.g. tqdm's monitor, may end: not counted)
            started = set(os.listdir("/proc/self/task")) - before
            assert len(started) == 1, started
    finally:
        torch.set_num_threads(threads)


def test_file_job_reports_a_bad_input_and_goes_on(tmp_path, capsys):
    """d2turb.io.jobs.FileJob, the skeleton of simulate and restore: one error line per bad input (naming it),
    the others processed and written, the summary line and the exit status; fail_fast (or one input) raises."""
    from d2turb.io import FileJob

    def work(path):
        if path.stem == "bad":
            raise D2TurbError("cannot read it")
        return path.stem.upper()

    paths = [tmp_path / "a.png", tmp_path / "bad.png", tmp_path / "c.png"]
    with FileJob("demo", len(paths), max_pending=2) as job:
        for path, result in job.each(paths, work, named=True, desc="demo", unit="img"):
            job.submit(write_json, tmp_path / f"{path.stem}.json", {"result": result})
    assert job.finish() == 1
    err = capsys.readouterr().err
    assert f"error: {tmp_path / 'bad.png'}: cannot read it" in err
    assert "demo: 2 of 3 inputs done, 1 failed (see the error lines)" in err
    assert sorted(p.name for p in tmp_path.glob("*.json")) == ["a.json", "c.json"]
    with FileJob("demo", 2, max_pending=2) as job:
        assert list(job.each(paths[1:2] * 2, work)) == []  # unnamed: the error as raised
    assert job.finish() == 2
    assert "error: cannot read it" in capsys.readouterr().err
    for total, fail_fast in ((3, True), (1, False)):
        with (
            pytest.raises(D2TurbError, match="bad.png: cannot read it"),
            FileJob("demo", total, fail_fast, max_pending=1) as job,
        ):
            list(job.each(paths, work, named=True))
