"""trackplot: gate table rows (pass direction, shared/stacked gates) and draw_track on an axes."""

from __future__ import annotations

import math

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pytest  # noqa: E402

from cfrace.track import load_track  # noqa: E402
from cfrace.trackplot import VIEWS, direction_text, draw_track, gate_rows, pass_direction  # noqa: E402


def test_pass_direction_is_minus_normal():
    assert pass_direction(0.0) == pytest.approx((-1.0, 0.0))
    assert pass_direction(math.pi / 2) == pytest.approx((0.0, -1.0))
    assert direction_text(pass_direction(-math.pi / 2)).startswith("+y")
    assert direction_text(pass_direction(-math.pi / 4)).startswith("-x+y")
    assert "-0.00" not in direction_text(pass_direction(-1.5708))


def test_gate_rows_notes():
    lt = gate_rows(load_track("lemniscate"))
    assert [r.notes for r in lt] == ["", "same physical gate as #4", "", "", "same physical gate as #1", ""]
    ct = gate_rows(load_track("complex"))
    assert ct[2].notes == "stacked with #3 (frames overlap)" and ct[3].notes == "stacked with #2 (frames overlap)"
    assert [r.notes for r in ct if r.index not in (2, 3)] == [""] * 4
    assert ct[4].yaw_deg == pytest.approx(180.0, abs=0.01) and ct[4].direction_text.startswith("+x")


@pytest.mark.parametrize("view", sorted(VIEWS))
def test_draw_track_sets_limits_and_draws_gates(view):
    t = load_track("complex")
    fig, ax = plt.subplots()
    draw_track(ax, t, True, view=view)
    h, v = VIEWS[view]
    lo = (t.arena.x[0], t.arena.y[0], 0.0)[h]
    assert ax.get_xlim()[0] < lo and ax.get_xlabel() == f"{'xyz'[h]} [m]" and ax.get_ylabel() == f"{'xyz'[v]} [m]"
    labels = sorted(txt.get_text() for txt in ax.texts if txt.get_text().replace(",", "").isdigit())
    assert set(",".join(labels).split(",")) == {str(i) for i in range(6)}  # every gate numbered once
    assert len(ax.patches) >= 4  # arena + obstacles (+ frames in the side views)
    plt.close(fig)


def test_draw_track_rejects_unknown_view():
    fig, ax = plt.subplots()
    with pytest.raises(ValueError, match="view"):
        draw_track(ax, load_track("lemniscate"), False, view="iso")
    plt.close(fig)
