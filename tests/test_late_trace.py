"""rig.late_trace: the causes of a late or slow cycle read off the kernel's trace (perf script lines made here:
the classification, not perf, is under test)."""

from __future__ import annotations

from rig.late_trace import classify, parse

CYCLE, HELPER, OTHER = 100, 101, 555  # the cycle thread, another thread of its process, another process
MARGIN_S = 200e-6


def _waking(t: float, by: int, comm: str = "python") -> str:
    return f"{comm} {by} [001] {t:.6f}: sched:sched_waking: comm=python pid={CYCLE} prio=49 target_cpu=001"


def _switch(t: float, state: str, to: int = OTHER) -> str:
    return (
        f"python {CYCLE} [001] {t:.6f}: sched:sched_switch: prev_comm=python prev_pid={CYCLE} prev_prio=49"
        f" prev_state={state} ==> next_comm=hog next_pid={to} next_prio=120"
    )


def _fault(t: float) -> str:
    return f"python {CYCLE} [001] {t:.6f}: exceptions:page_fault_user: address=0x7f00 ip=0x7f01 error_code=0x7"


def _causes(lines: list[str], window: tuple[str, float, float]) -> list[str]:
    return classify(parse("\n".join(lines)), window, CYCLE, {CYCLE, HELPER}, MARGIN_S)["causes"]


def test_a_wake_up_that_came_late_is_the_timer_s() -> None:
    deadline = 10.0
    lines = [_waking(deadline - MARGIN_S + 0.0014, 0, "swapper/1")]  # 1.4 ms after it was due
    assert _causes(lines, ("late", deadline, deadline + 0.0012)) == ["timer_late"]


def test_on_time_and_on_the_cpu_throughout_is_the_host_s() -> None:
    deadline = 10.0
    lines = [_waking(deadline - MARGIN_S + 0.000005, 0, "hog")]
    assert _causes(lines, ("late", deadline, deadline + 0.0015)) == ["host"]


def test_sleeping_until_another_thread_of_the_process_wakes_it_is_the_gil() -> None:
    start = 20.0
    lines = [_switch(start + 0.0001, "S"), _waking(start + 0.0009, HELPER), _fault(start + 0.00095)]
    assert _causes(lines, ("slow", start, start + 0.001)) == ["gil", "page_faults"]


def test_switched_out_runnable_is_preempted_and_woken_from_outside_is_blocked() -> None:
    start = 30.0
    assert _causes([_switch(start + 0.0001, "R")], ("slow", start, start + 0.001)) == ["preempted"]
    lines = [_switch(start + 0.0001, "S"), _waking(start + 0.0008, OTHER, "other")]
    assert _causes(lines, ("slow", start, start + 0.001)) == ["blocked"]


def test_the_clock_s_own_sleep_before_the_deadline_is_not_a_cause() -> None:
    deadline = 40.0
    lines = [
        _switch(deadline - 0.0015, "S"),
        _waking(deadline - MARGIN_S + 0.00001, 0, "swapper/1"),
        _fault(deadline - 0.0015),
    ]
    assert _causes(lines, ("late", deadline, deadline + 0.0003)) == ["host"]


def test_a_slow_cycle_the_kernel_saw_nothing_of_was_on_its_cpu() -> None:
    assert _causes([], ("slow", 50.0, 50.001)) == ["cpu"]
