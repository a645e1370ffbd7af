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


def test_pooled_means_are_inverse_variance_and_the_table_skips_the_reference():
    """Two experiments at 1 and 3 mm with std 100 and 300 µm pool to 1.2 mm ± 94.9 µm (1/√(1/0.1² + 1/0.3²)
    mm); the reference IMU (zero std) gets no row; one column per variant present."""
    a = _rec([[0.0, 0, 0], [1e-3, 0, 0], [0, 0, 0], [0, 0, 0]], std=1e-4, exp=1)
    b = _rec([[0.0, 0, 0], [3e-3, 0, 0], [0, 0, 0], [0, 0, 0]], std=3e-4, exp=2)
    mean, sd, med = mmc.pooled_means([a, b])
    np.testing.assert_allclose(mean[1, 0], 1.2e-3, rtol=1e-12)
    np.testing.assert_allclose(sd[1, 0], (1 / 1e-8 + 1 / 9e-8) ** -0.5, rtol=1e-12)
    np.testing.assert_allclose(med[1, 0], 2e-4, rtol=1e-12)
    L = mmc.means_table({"without": [a, b], "with": [a, b]})
    rows = [ln for ln in L if ln.startswith("| r[")]
    assert len(rows) == 9 and not any(ln.startswith("| r[0,") for ln in rows)
    assert rows[0] == "| r[1, x] | 1.200 ± 95 (200) | 1.200 ± 95 (200) | 10.000 |"
