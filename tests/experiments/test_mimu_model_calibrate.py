"""experiments/mimu_model_calibrate.py: the with_acc comparison on hand-made records (the real run is the
study itself)."""
import numpy as np

from experiments import mimu_model_calibrate as mmc

# a two-layer board: IMU 0 the reference (upper), 1 and 3 below it by 2 mm, 2 upper
NOMINAL = [[0.0, 0, 0], [0.01, 0, -0.002], [0.02, 0, 0], [0.03, 0, -0.002]]


def _rec(mean, std=1e-4, exp=1, **kw):
    return {"exp": exp, "mean": mean, "std": [[0.0, 0, 0]] + [[std] * 3] * 3, "nominal": NOMINAL, **kw}


def test_layer_shift_is_the_lower_layers_motion_against_the_upper():
    """A shift of the lower IMUs alone reads as itself; one of every IMU (a translation) reads as zero;
    the reference IMU is left out of the upper layer's mean."""
    base = np.array(NOMINAL)
    moved = base.copy()
    moved[[1, 3], 0] += 150e-6
    moved[[1, 3], 1] -= 80e-6
    np.testing.assert_allclose(mmc.layer_shift_um(_rec(moved.tolist()), _rec(base.tolist())), [150, -80], atol=1e-6)
    np.testing.assert_allclose(mmc.layer_shift_um(_rec((base + 1e-4).tolist()), _rec(base.tolist())), [0, 0],
                               atol=1e-6)
    up = base.copy()
    up[2, 0] += 40e-6  # the upper IMU moves: the lower layer reads −40 against it
    np.testing.assert_allclose(mmc.layer_shift_um(_rec(up.tolist()), _rec(base.tolist()))[0], -40, atol=1e-6)


def test_acc_table_has_one_row_per_experiment_with_the_blocks_record():
    base = np.array(NOMINAL)
    moved = base.copy()
    moved[[1, 3], 0] += 200e-6
    w = _rec(base.tolist(), untempered_ratio_max=1.1)
    a = _rec(moved.tolist(), untempered_ratio_max=1.2, acc_blocks={"tau_matrix": 0.004, "tau_bias_m_s2": 0.2},
             sandwich_before_blocks={"std_ratio_max": 1.1})
    md = mmc.acc_markdown({"with": [w], "with_acc": [a]}, {})
    rows = [ln for ln in md.splitlines() if ln.startswith("| 1 |")]
    assert len(rows) == 1
    assert "0.40 / 0.200" in rows[0] and "(+200, +0)" in rows[0] and "1.10 → 1.20" in rows[0]
    # z of the difference: 200 µm over √2·100 µm on two coordinates of nine
    z = 200 / np.sqrt(2 * 1e-8 * 1e12)
    assert f"{np.sqrt(2 * z ** 2 / 9):.2f} / {z:.2f}" in rows[0]
