"""The CLI's progress bars: a finished stage's clock stops."""

from __future__ import annotations

from rich.progress import Progress, TimeElapsedColumn

from deepmapping.cli.progress import Callbacks, progress_bar


def _task(cb: Callbacks, name: str):
    return next(t for t in cb.bar.tasks if t.id == cb.tasks[name])


def test_the_warm_start_clock_stops_when_training_begins():
    now = [0.0]
    cb = Callbacks(Progress(TimeElapsedColumn(), get_time=lambda: now[0], disable=True))
    for i in range(1, 16):  # 2D incremental ICP: scans 1 ... K-1 of K = 16, 0.2 s each
        cb.icp(i, 16)
        now[0] += 0.2
    cb.epoch(1, 250, 0.9)  # training begins: the warm start is over
    for epoch in range(2, 251):
        now[0] += 0.6  # 150 s of training
        cb.epoch(epoch, 250, 0.5)
    icp, train = _task(cb, "warm start / ICP"), _task(cb, "training")
    assert icp.finished and icp.completed == 16 and abs(icp.elapsed - 3.0) < 1e-6
    assert str(TimeElapsedColumn().render(icp)) == "0:00:03"  # not 0:02:32, the whole run
    assert train.finished and abs(train.elapsed - 149.4) < 1e-6  # 250 of 250
    cb.stop()
    now[0] += 60
    assert abs(train.elapsed - 149.4) < 1e-6 and train.completed == 250


def test_three_stages_each_keep_their_own_time():
    now = [0.0]
    cb = Callbacks(Progress(get_time=lambda: now[0], disable=True))
    cb.icp(1, 2)
    now[0] += 1
    cb.place(1, 4)  # the second stage begins: ICP stops at 1 s
    now[0] += 2
    cb.epoch(1, 10, 0.1)  # the third: placing stops at 2 s, ICP stays at 1 s
    now[0] += 5
    assert [round(_task(cb, n).elapsed, 6) for n in cb.tasks] == [1.0, 2.0, 5.0]


def test_leaving_the_progress_bar_stops_every_clock_as_it_stands():
    with progress_bar(enabled=False) as cb:
        cb.icp(1, 4)
        cb.epoch(3, 10, 0.2)
    icp, train = _task(cb, "warm start / ICP"), _task(cb, "training")
    assert icp.stop_time is not None and icp.completed == 4  # over when training began
    assert train.stop_time is not None and train.completed == 3 and not train.finished  # e.g. interrupted
