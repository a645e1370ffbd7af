"""The diagnosis of ``experiments/vibgeom_probe.py`` (issue #30 item 4): the concealed recordings'
accelerometer misfit is the high-frequency motion seen at different sampling instants, not the
filter's rectification of the centripetal term."""
from experiments import vibgeom_probe as vp


def test_the_misfit_vanishes_when_every_imu_samples_at_the_read_instant():
    # clock-010's draw (plate4, 100 Hz; 8 s: one move), noise-free: as drawn the projected misfit
    # at the true positions is as large as the centripetal signal; the twin (same motion and DLPF,
    # ticks on the reads) leaves a few mm/s², so the ages — not LPF(u(ω)) ≠ u(LPF(ω)) — carry it
    drawn = vp.misfit(10, {}, duration=8.0)
    twin = vp.misfit(10, {"kind": "twin"}, duration=8.0)
    assert drawn["misfit_rms"] > 0.1 and drawn["misfit_rms"] > 0.5 * drawn["signal_rms"], drawn
    assert twin["misfit_rms"] < 0.05 * twin["signal_rms"], twin
