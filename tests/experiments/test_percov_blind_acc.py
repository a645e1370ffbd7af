"""``experiments/percov_blind_acc.py``: its document's pooled figures against numpy on made-up cases."""
import numpy as np

from experiments import percov_blind_acc as pb


def _row(seed, z, err_um, std_um, variant, truth_mm=None):
    return {"variant": variant, "seed": seed, "board": "cube6", "f_host": 125.0, "K": 6, "acc_blocks": [0, 1, 2],
            "detect_seconds": 50.0, "calibrate_seconds": 20.0,
            "score": {"z": list(z), "error_m": [e * 1e-6 for e in err_um], "std_m": [s * 1e-6 for s in std_um],
                      "coordinates": [f"r[{i}, x]" for i in range(len(z))],
                      "truth_m": [t * 1e-3 for t in (truth_mm or [10.0 * (i + 1) for i in range(len(z))])]}}


def test_pooled_figures_and_the_bar():
    zb = [[0.5, -1.0, 1.5], [0.2, 4.5, -0.3]]
    zo = [[1.0, 1.0, 1.0], [1.0, -1.0, 1.0]]
    rows = [(_row(s, zb[s], [10, 20, 30], [100, 100, 200], "blind"), _row(s, zo[s], [1, 2, 3], [50, 50, 50], "oracle"))
            for s in range(2)]
    rows.append((_row(2, [9.0], [1], [1], "blind"), None))  # no oracle: left out of the pooled figures
    L = "\n".join(pb.markdown(rows, "cmd", 1.0))
    allb = np.concatenate(zb)
    assert f"| error/std RMS (must: 0.8–1.25) | {np.sqrt(np.mean(allb ** 2)):.2f} | 1.00 |" in L
    assert "| coordinates beyond 4 std (must: 0) | 1/6 | 0/6 |" in L
    assert "| bar met | NO | YES |" in L
    assert f"| RMS error (µm) | {np.sqrt(np.mean(np.square([10, 20, 30] * 2))):.1f} |" in L
    assert "Cases: 2 with both (3 run)." in L and "| clock-002 | cube6 | 125 | 3/6 | 9.00 / — |" in L


def test_whole_array_rescale_is_taken_out():
    # estimates exactly 2 % too large: size +2.00 %, nothing left after the rescale
    t = np.array([10.0, -20.0, 30.0])  # mm
    err_um = list(0.02 * t * 1e3)
    std_um = [50.0, 50.0, 50.0]
    b = _row(0, list(np.array(err_um) / 50.0), err_um, std_um, "blind", truth_mm=list(t))
    size, z = pb.rescaled(b["score"])
    assert abs(size - 0.02) < 1e-12 and np.abs(z).max() < 1e-9
    # plus an error orthogonal to the truth: it stays, in std units
    extra = np.array([30.0, 15.0, 0.0])  # µm, orthogonal to t
    assert abs(extra @ t) < 1e-12
    b["score"]["error_m"] = list((np.array(err_um) + extra) * 1e-6)
    size, z = pb.rescaled(b["score"])
    assert abs(size - 0.02) < 1e-12
    np.testing.assert_allclose(z, extra / 50.0, atol=1e-9)
    L = "\n".join(pb.markdown([(b, _row(0, [1.0, 1.0, 1.0], [1, 2, 3], [50, 50, 50], "oracle"))], "cmd", 1.0))
    assert f"| z RMS after each case's whole-array rescale | {np.sqrt(np.mean((extra / 50) ** 2)):.2f} |" in L
    assert "| +2.00 / " in L


def test_gyro_common_reads_the_stage_record():
    M = [[0.01, 0.2, 0.0], [0.0, -0.04, 0.0], [0.0, 0.0, 0.0]]
    kept = pb.gyro_common({"details": {"gyro_linear_stage": {"common": {"matrix": M, "bias": [0, 0, 0], "kept": True}}}})
    assert kept == {"kept": True, "max_abs": 0.2, "isotropic": -0.01}
    assert pb.gyro_common({"details": {"gyro_linear_stage": {"result": "no blocks"}}}) == {"kept": False}
    assert pb.gyro_common({"details": {}}) == {"kept": False}
    b = _row(0, [1.0], [1], [1], "blind")
    b["gyro_common"] = kept
    L = "\n".join(pb.markdown([(b, _row(0, [1.0], [1], [1], "oracle"))], "cmd", 1.0))
    assert "| 0.200 (-1.0 %) / ? |" in L


def test_blocks_fixed_column_appears_with_every_case():
    zb, zo, zf = [0.5, -1.0, 1.5], [1.0, 1.0, 1.0], [3.0, -4.5, 1.0]
    b = _row(0, zb, [10, 20, 30], [100, 100, 200], "blind")
    b["acc_blocks_record"] = {"tau_matrix": 0.006, "tau_bias_m_s2": 0.08}
    rows = [(b, _row(0, zo, [1, 2, 3], [50, 50, 50], "oracle"), _row(0, zf, [1, 2, 3], [1, 1, 1], "blind_fixed"))]
    L = "\n".join(pb.markdown(rows, "cmd", 1.0))
    assert f"| error/std RMS (must: 0.8–1.25) | {np.sqrt(np.mean(np.square(zb))):.2f} | 1.00 | " \
           f"{np.sqrt(np.mean(np.square(zf))):.2f} |" in L
    assert "| coordinates beyond 4 std (must: 0) | 0/3 | 0/3 | 1/3 |" in L
    assert f" {np.sqrt(np.mean(np.square(zf))):.2f} / 4.50 | 0.60 / 0.080 |" in L
    # without a blocks-fixed record for every pooled case the column is left out
    L2 = "\n".join(pb.markdown([rows[0][:2]], "cmd", 1.0))
    assert "blocks fixed" not in L2


def test_the_targets_sandwich_line_uses_the_sandwich_and_the_cuts_spread():
    """Error 30, 40 µm against a sandwich std of 100 µm (sandwich order reversed, matched by name) and a cut of
    0 / 100 µm: error over √(sandwich² + cut²) = 0.3, 0.283 (RMS 0.29, under 0.8: the 'overstates' reading)."""
    b = _row(0, [0.3, 0.4], [30, 40], [100, 100], "blind")
    b["sandwich"] = {"coordinates": ["r[1, x]", "r[0, x]"], "sandwich_std_m": [1e-4, 1e-4], "cut_std_m": [1e-4, 0.0],
                     "std_ratio_max": 5.0, "std_ratio_median": 3.0}
    o = _row(0, [1.0, 1.0], [1, 2], [1, 1], "oracle")
    L = "\n".join(pb.markdown([(b, o)], "cmd", 1.0))
    want = np.sqrt(np.mean([0.3 ** 2, (0.4 / np.sqrt(2)) ** 2]))
    assert f"has RMS {want:.2f} (max 0.30, 0 beyond 4), where over the posterior std it is 0.35." in L
    assert "std ratio max 5.00–5.00" in L
    # the oracle's own sandwich (no cut): errors 1, 2 µm over 0.5 µm → 2, 4 (RMS 3.16, none beyond 4)
    o["sandwich"] = {"coordinates": ["r[0, x]", "r[1, x]"], "sandwich_std_m": [5e-7, 5e-7],
                     "std_ratio_max": 1.0, "std_ratio_median": 1.0}
    L = "\n".join(pb.markdown([(b, o)], "cmd", 1.0))
    assert "the oracle's (the per-sample likelihood's own sandwich) 3.16 (max 4.00, 0 beyond 4) against 1.00." in L
