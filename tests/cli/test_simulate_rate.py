"""`simulate --rate` is bounded to physical output rates: an absurd rate is refused at parse time
(exit 2, one line naming the option) and nothing is written."""
import subprocess
import sys


def _run(tmp_path, rate):
    out = tmp_path / "r.nc"
    p = subprocess.run([sys.executable, "-m", "accel_bayes.cli", "simulate", "--preset", "mimu32", "-T", "20",
                        "--rate", rate, "--seed", "1", "-o", str(out)], capture_output=True, text=True)
    return p, out


def test_absurd_rate_refused(tmp_path):
    p, out = _run(tmp_path, "1e300")
    assert p.returncode == 2
    lines = [ln for ln in p.stderr.strip().splitlines() if ln.strip()]
    assert "--rate" in lines[-1] and "100000" in lines[-1]
    assert "Traceback" not in p.stderr
    assert not out.exists()


def test_upper_bound_rate_accepted(tmp_path):
    p, out = _run(tmp_path, "100000")
    assert p.returncode == 0, p.stderr
    assert out.exists()
