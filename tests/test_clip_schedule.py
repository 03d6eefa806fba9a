"""d2turb.clip.schedule.in_order: results in order, a ready one passed on before the next job is made."""

from concurrent.futures import Future

from d2turb.clip.schedule import in_order


def test_a_ready_value_is_passed_on_before_the_next_job_is_made():
    made = []

    def jobs():
        for i in range(3):
            made.append(i)
            yield i * 10

    it = in_order(jobs())
    assert next(it) == 0 and made == [0]  # the first output does not wait for the second to be computed
    assert list(it) == [10, 20] and made == [0, 1, 2]


def test_futures_keep_their_order_with_one_more_in_flight():
    futures = [Future() for _ in range(3)]
    first_done_when_second_asked = []

    def jobs():
        yield futures[0]
        first_done_when_second_asked.append(futures[0].done())
        futures[0].set_result("a")
        yield futures[1]
        futures[1].set_result("b")
        yield futures[2]
        futures[2].set_result("c")

    assert list(in_order(jobs())) == ["a", "b", "c"]
    assert first_done_when_second_asked == [False]  # the next job is made while the first is still running


def test_a_finished_future_is_passed_on_at_once():
    done = Future()
    done.set_result("x")
    made = []

    def jobs():
        made.append(0)
        yield done
        made.append(1)
        yield "y"

    it = in_order(jobs())
    assert next(it) == "x" and made == [0]
    assert list(it) == ["y"]


def test_what_is_queued_when_the_caller_stops_is_cancelled():
    first, queued, never = Future(), Future(), Future()

    def jobs():
        yield first
        first.set_result("a")
        yield queued
        yield never

    it = in_order(jobs())
    assert next(it) == "a"
    it.close()
    assert queued.cancelled() and not never.cancelled()  # the one made is cancelled; the next was never asked for
