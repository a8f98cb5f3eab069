"""make test's scheduling (tests/conftest.py): the tests marked slow are found, and handed out first."""

from __future__ import annotations

from tests.conftest import CostliestFirst, is_slow, xdist_scope


def test_slow_marks_are_read_from_functions_and_modules() -> None:
    assert is_slow("tests/test_demo.py::test_demo_reduces_rms_error")  # @pytest.mark.slow
    assert not is_slow("tests/test_demo.py::test_duration_flag_stops_early")
    assert is_slow("tests/packaging/test_deb.py::test_lintian_reports_no_error_and_every_override_is_used[compd]")
    assert is_slow("tests/closedloop/test_lathe.py::test_lathe_ar1_paper_form_closed_loop_cuts_the_error")
    assert not is_slow("tests/test_scheduling.py::test_slow_marks_are_read_from_functions_and_modules")


def test_the_costliest_unit_goes_first_and_ties_keep_their_order() -> None:
    units = [
        "tests/test_scheduling.py::test_a",
        "tests/packaging/test_deb.py",
        "tests/test_demo.py::test_duration_flag_stops_early",
        "tests/test_demo.py::test_demo_reduces_rms_error",
        "tests/cycle/test_loop.py::test_word_walks_one_lsb_at_the_slew_pace",
    ]
    queue = CostliestFirst()
    for unit in units:
        ids = [f"{unit}::test_{k}" for k in range(8)] if unit.endswith(".py") else [unit]
        queue[unit] = dict.fromkeys(ids, False)
    order = [queue.popitem(last=False)[0] for _ in units]
    assert order == [units[1], units[3], units[4], units[0], units[2]]
    assert xdist_scope("tests/linuxcnc/test_sim.py::test_x") == "linuxcnc"
