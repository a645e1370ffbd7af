"""A finding whose effect a later detector step withdrew leaves the report (detector step 7a:
``timing_wander`` superseded by ``unresolved_motion``'s age error).  Until 2026-11-28 the filter read
``Finding.effect`` — the vocabulary *name* — as if it were the fitted effect, matched nothing, and
real-data reports kept three superseded ``timing_wander`` findings each, which ``calibrate --model``
then read as per-sample covariances on top of the unresolved motion that replaced them."""
from accel_bayes.mismatch.detector import without_withdrawn
from accel_bayes.mismatch.report import Finding
from accel_bayes.physics.effects import make_effect


def _finding(effect):
    return Finding(effect=effect, evidence=100.0, df=3, log10_p=-20.0, where={}, explanation="")


def test_withdrawn_findings_leave_the_report_and_only_they():
    wander_gyro = make_effect("timing_wander", imu=2, sensor="gyro")
    wander_acc = make_effect("timing_wander", imu=7, sensor="acc")
    same_imu_other_sensor = make_effect("timing_wander", imu=2, sensor="acc")
    bias = make_effect("gyro_bias", imu=2, axis="x")
    findings = [_finding(e) for e in (wander_gyro, wander_acc, same_imu_other_sensor, bias)]
    gone = [{"effect": wander_gyro.label(), "reason": "superseded"},
            {"effect": wander_acc.label(), "reason": "superseded"}]
    kept = without_withdrawn(findings, gone)
    assert [f.model for f in kept] == [same_imu_other_sensor, bias]
    # the names the report writes are unchanged for what stays
    assert [f.effect for f in kept] == ["timing_wander", "gyro_bias"]


def test_nothing_withdrawn_keeps_every_finding():
    findings = [_finding(make_effect("timing_wander", imu=k, sensor="gyro")) for k in range(3)]
    assert without_withdrawn(findings, []) == findings
