"""SharedJobs (flakedb/rt/common/jobs.py), which the rough top's build shares with the solver's main thread.

Guards against: a job run twice or never when a helper thread takes jobs meanwhile, results out of the
listed order, a helper that blocks (it must return when nothing is left), and a job's error lost."""

import threading

import pytest

from flakedb.rt.common.jobs import SharedJobs


def test_a_helper_takes_the_jobs_not_yet_started_and_results_keep_their_order():
    jobs = SharedJobs()
    started, release = threading.Event(), threading.Event()
    ran = []

    def first():
        started.set()
        assert release.wait(10)
        ran.append(("first", threading.current_thread().name))
        return "first"

    def later(k):
        ran.append((k, threading.current_thread().name))
        return k

    owner = {}
    t = threading.Thread(target=lambda: owner.setdefault("out", jobs.run([(first, (), {})] +
                                                                           [(later, (k,), {}) for k in range(4)])),
                         name="owner")
    t.start()
    assert started.wait(10)
    jobs.help()  # the owner is stuck in its first job: this thread takes the four others
    release.set()
    t.join(10)
    assert owner["out"] == ["first", 0, 1, 2, 3]
    assert sorted(k for k, _ in ran if k != "first") == [0, 1, 2, 3] and len(ran) == 5  # each exactly once
    assert {name for k, name in ran if k != "first"} == {threading.current_thread().name}
    jobs.help()  # nothing left: returns at once


@pytest.mark.parametrize("threads", [1, 3])
def test_workers_give_the_serial_results_and_errors_reach_the_caller(threads):
    jobs = SharedJobs(threads)
    assert jobs.run([(pow, (k, 2), {}) for k in range(20)]) == [k * k for k in range(20)]

    def fail():
        raise ValueError("a part failed")

    with pytest.raises(ValueError, match="a part failed"):
        jobs.run([(pow, (2, 3), {}), (fail, (), {}), (pow, (3, 2), {})])
