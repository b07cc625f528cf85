"""The seeded sweep of boxes outside the registry (``python -m hvac_mpc.benchmarks.box_sweep``; docs/robustness.md
sec. 2.19): the draw repeats, stays within its ranges, and each box's ``--box`` text gives the same box back."""

import pytest

from hvac_mpc.benchmarks import box_sweep, mismatch_suite


def test_the_draw_repeats_and_stays_in_its_ranges():
    boxes = box_sweep.draw_boxes(0, 14)
    assert boxes == box_sweep.draw_boxes(0, 14)
    assert box_sweep.draw_boxes(0, 5) == boxes[:5]  # a larger count keeps the first boxes
    assert box_sweep.draw_boxes(1, 14) != boxes
    for _, v in boxes:
        assert box_sweep.TRANSPORT_DELAY_S[0] <= v.transport_delay_s <= box_sweep.TRANSPORT_DELAY_S[1]
        assert box_sweep.DUCT_LOSS_UA_W_PER_K[0] <= v.duct_loss_ua_w_per_k <= box_sweep.DUCT_LOSS_UA_W_PER_K[1]
        for name, (lo, hi) in box_sweep.RANGES.items():
            assert lo <= getattr(v, name) <= hi
    literal = [v.cooler_literal_fit for _, v in boxes]
    assert any(literal) and not all(literal)


def test_the_box_option_reads_back_to_the_same_box():
    for label, v in box_sweep.draw_boxes(3, 8):
        assert mismatch_suite.parse_box(box_sweep.box_option(label, v)) == (label, v)


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="count"):
        box_sweep.draw_boxes(0, 0)
    with pytest.raises(ValueError, match="seed"):
        box_sweep.draw_boxes(-1, 3)
    assert box_sweep.main(["--only", "nope", "--list"]) == 2
    with pytest.raises(ValueError, match=r"MpcSettings\.ekf: unknown field\(s\) \['nope'\]"):
        box_sweep.mpc_factory_with(ekf={"nope": 1})


def test_sweep_summary_counts_cells_above_the_limit():
    results = {"variants": {"A": {"x": {"temp_iae_cs": 0.5}, "y": {"temp_iae_cs": 1.2}},
                            "B": {"x": {"temp_iae_cs": 0.9}, "y": {"temp_iae_cs": None}}}}
    s = box_sweep.sweep_summary(results)
    assert s["cells"] == 3 and s["above_limit"] == 1 and s["worst_cell"] == "A / y"
    assert s["median"] == pytest.approx(0.9)
