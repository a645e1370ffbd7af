#!/usr/bin/env python3
"""Benchmark: cost of one log p̂ and of one PmMH iteration (issue #15 item 2), ours against the
code of an earlier commit (the peer, default 368b126) run from a separate worktree.

Both run as worker subprocesses of this script (``--worker``), one imported from this checkout,
the other from ``--peer`` (a ``git worktree`` of the peer commit), each with one torch thread.
The driver alternates them: in every round each worker times a block of calls in turn, so both
see the same machine load; the printed numbers are medians over all blocks' calls (wall clock).
Before timing, both evaluate log p̂ on the same standard normals (``sample_z`` with one seed, the
same in both versions) and the relative difference is printed.

Cases (``--cases``):

* ``exp1`` — the real MIMU4444 recording exp_1 (8 IMUs, T = 5885) through the preparation of
  ``calibrate`` (:func:`accel_bayes.prep.preprocess.preprocess`), N = 1, at the nominal
  positions; stated noise and the eq. 30 gyro posterior (``calibrate`` would estimate the noise
  and use the calibrated posterior: same cost); skipped when the shared data are absent.
* ``mimu8`` — simulated 8-corner MIMU4444, ``smooth`` motion, T = 5900, N = 1 (exp_1-like).
* ``plate7`` — 7 of those IMUs, T = 2600, N = 25.
* ``mimu32`` — the 32-IMU board, [C21] §IV-A i.i.d. motion, σ_a = 0.04 m/s², T = 500, N = 1
  (what ``choose_num_draws`` picks there: Var[log p̂] ≈ 0.1 at N = 1).
* ``mimu32k`` — the same with N = 1000 (bench_likelihood.py's setting; log p̂ only).

One iteration is :meth:`PMMHKernel.sample` after warm-up (mixture proposal, independence
probability 0.3, MAP-like centre = the true/nominal positions): propose, prior, one fresh
log p̂, accept/reject.

    python experiments/bench_iteration.py [--peer /work/h2base] [--rounds 15] [--block 20]
    python experiments/bench_iteration.py --device cuda [--cases exp1,mimu8,plate7,mimu32,mimu32k]

Output ends with lines ``RESULT <name>: ours x ms, peer y ms, speedup rx``.

``--device DEV`` (issue #15 item 4) runs "ours" with the likelihood, its standard normals, the prior
and the kernel's generator on DEV, and the peer is this same checkout on the CPU (``--peer`` is then
ignored): the RESULT lines read ``RESULT <name>[DEV]: ours x ms (DEV), peer y ms (cpu), speedup rx``.
Times on a GPU include a ``torch.cuda.synchronize()`` after every call (otherwise only the kernel
launches would be timed), and log p̂ on the same z is compared between the devices before timing.
The CPU stays the default; nothing else in the package needs a GPU.  That the hot path creates no
tensor on the wrong device is tested without a GPU (tests/mcmc/test_device.py).
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
NOEDITABLE = "/tmp/noeditable"  # hides an editable install of another checkout, where present


# ---------------------------------------------------------------------------- worker side

def _build(name, device="cpu"):
    import torch
    from accel_bayes.model.likelihood import RaoBlackwellLikelihood
    from accel_bayes.prep.prepared import prepare_recording
    from accel_bayes.physics import arrays
    from accel_bayes.simulate import simulate

    if name == "exp1":
        sys.path.insert(0, str(HERE))
        from _data import data_dir
        from accel_bayes.data.mimu import import_mimu
        from accel_bayes.prep.preprocess import preprocess

        path = data_dir() / "exp_1" / "data.bin.gz"
        if not path.exists():
            return None
        pre = preprocess(import_mimu(path))
        rec = pre.recording
        lik = RaoBlackwellLikelihood.from_recording(prepare_recording(rec, selection=pre.selection), num_draws=1,
                                                    device=device)
        return lik, lik.nominal_positions.clone().to(device)
    if name in ("mimu8", "plate7"):
        T, N, seed = (5900, 1, 1) if name == "mimu8" else (2600, 25, 2)
        sim = simulate(arrays.mimu4444_8(), "smooth", T=T, seed=seed)
        acc = None if name == "mimu8" else list(range(7))
        lik = RaoBlackwellLikelihood.from_recording(prepare_recording(sim.recording, acc_imus=acc), num_draws=N,
                                                    device=device)
    elif name in ("mimu32", "mimu32k"):
        sim = simulate(arrays.mimu4444_32(), "iid", T=500, seed=3, position_error_std=0.0, acc_noise_std=0.04,
                       clip=False)
        lik = RaoBlackwellLikelihood.from_recording(sim.recording, num_draws=1000 if name == "mimu32k" else 1,
                                                    gyro_method="calibrated", device=device)
    else:
        raise SystemExit(f"unknown case {name!r}")
    return lik, sim.true_positions[list(lik.imu_labels)].clone().to(device)


def _kernel(lik, pos):
    import torch
    from accel_bayes.inference.mcmc import PMMHKernel
    from accel_bayes.inference.mcmc.priors import GaussianPrior
    from accel_bayes.model.likelihood import theta_from_positions

    th = theta_from_positions(pos, lik.reference)
    d = th.numel()
    cov = torch.eye(d, dtype=torch.float64, device=pos.device) * (20e-6) ** 2
    prior = GaussianPrior(pos, std=3e-3, reference=lik.reference)
    k = PMMHKernel(lik, prior, seed=3, proposal_cov=cov, independence_prob=0.3, independence_mean=th,
                   independence_cov=cov, step_size=0.5)
    k.initial_params = {"r": th}
    k.setup(0)
    return k


def worker():
    import torch

    torch.set_num_threads(1)
    built = {}
    for line in sys.stdin:
        cmd = json.loads(line)
        op, name, device = cmd["op"], cmd["case"], cmd.get("device", "cpu")
        if (name, device) not in built:
            b = _build(name, device) if device != "cpu" else _build(name)  # cpu: exactly the calls of the stored runs
            built[name, device] = None if b is None else (*b, _kernel(*b))
        if built[name, device] is None:
            print(json.dumps({"missing": True}), flush=True)
            continue
        lik, pos, kern = built[name, device]
        sync = torch.cuda.synchronize if torch.device(device).type == "cuda" else (lambda: None)
        if op == "value":
            # the same normals on every device: drawn on the CPU with one seed, then moved
            z = lik.sample_z(generator=torch.Generator().manual_seed(123)) if device == "cpu" else \
                lik.to("cpu").sample_z(generator=torch.Generator().manual_seed(123)).to(device)
            P = pos.cpu() + 2e-4 * torch.randn(4, *pos.shape, generator=torch.Generator().manual_seed(7),
                                               dtype=pos.dtype)
            P[0] = pos.cpu()
            v = lik.log_phat(P.to(device), z=z).cpu()
            print(json.dumps({"value": [float(x) for x in v], "T": lik.T, "A": lik.A, "N": lik.num_draws}),
                  flush=True)
            continue
        if op == "logphat":
            gen = torch.Generator(device=device).manual_seed(1)
            fn = lambda: lik.log_phat(pos, generator=gen)  # noqa: E731
        else:
            fn = lambda: kern.sample({})  # noqa: E731
        fn()
        sync()
        ts = []
        for _ in range(int(cmd["reps"])):
            t0 = time.perf_counter()
            fn()
            sync()
            ts.append(time.perf_counter() - t0)
        out = {"times": ts}
        if op == "iteration":
            out["accept"] = kern.diagnostics()["acceptance rate"]
        print(json.dumps(out), flush=True)


# ---------------------------------------------------------------------------- driver side

class Worker:
    def __init__(self, tree):
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join(p for p in (str(tree), NOEDITABLE) if p)
        env["OMP_NUM_THREADS"] = "1"
        env["MKL_NUM_THREADS"] = "1"
        self.p = subprocess.Popen([sys.executable, str(Path(__file__).resolve()), "--worker"], stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, text=True, env=env, cwd=str(tree))

    def ask(self, **cmd):
        self.p.stdin.write(json.dumps(cmd) + "\n")
        self.p.stdin.flush()
        line = self.p.stdout.readline()
        if not line:
            raise SystemExit("worker died")
        return json.loads(line)

    def close(self):
        self.p.stdin.close()
        self.p.wait()


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--peer", type=Path, default=Path("/work/h2base"),
                    help="checkout of the peer commit (git worktree add <dir> 368b126)")
    ap.add_argument("--cases", default="exp1,mimu8,plate7,mimu32,mimu32k")
    ap.add_argument("--rounds", type=int, default=15, help="alternations ours/peer per measurement")
    ap.add_argument("--block", type=int, default=20, help="calls per worker per round")
    ap.add_argument("--device", default="cpu",
                    help="device of 'ours' (e.g. cuda); not cpu: the peer is this checkout on the CPU")
    args = ap.parse_args(argv)
    if args.worker:
        return worker()
    dev = args.device
    if dev != "cpu":
        import torch

        try:
            torch.empty(1, device=dev)
        except Exception as exc:  # noqa: BLE001 — any failure means the device is not usable here
            raise SystemExit(f"--device: {dev!r} is not usable here ({str(exc).splitlines()[0]})") from None
        args.peer = ROOT
    elif not (args.peer / "accel_bayes").is_dir():
        raise SystemExit(f"--peer {args.peer}: no accel_bayes there (git -C {ROOT} worktree add {args.peer} 368b126)")
    ours, peer = Worker(ROOT), Worker(args.peer)
    peer_rev = subprocess.run(["git", "-C", str(args.peer), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True).stdout.strip()
    ours_rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                              text=True).stdout.strip()
    print(f"ours {ROOT} ({ours_rev}) on {dev}, peer {args.peer} ({peer_rev}) on cpu; 1 torch thread each; "
          f"{args.rounds} rounds × {args.block} calls, alternating; medians of wall-clock times")
    tag, on = ("", "") if dev == "cpu" else (f"[{dev}]", f" ({dev})")
    results = []
    try:
        for name in args.cases.split(","):
            a, b = ours.ask(op="value", case=name, device=dev), peer.ask(op="value", case=name)
            if a.get("missing"):
                print(f"{name}: data not found, skipped")
                continue
            rel = max(abs(x - y) / abs(y) for x, y in zip(a["value"], b["value"]))
            print(f"{name}: T={a['T']} A={a['A']} N={a['N']}; log p̂ at 4 θ on the same z: ours {a['value'][0]:.6f}, "
                  f"peer {b['value'][0]:.6f}, max relative difference {rel:.1e}")
            ops = ["logphat"] if name == "mimu32k" else ["logphat", "iteration"]
            for op in ops:
                reps = max(3, args.block // 10) if name == "mimu32k" else args.block
                ta, tb, acc = [], [], None
                for r in range(args.rounds):
                    first, second = (ours, peer) if r % 2 == 0 else (peer, ours)
                    x = first.ask(op=op, case=name, reps=reps, **({"device": dev} if first is ours else {}))
                    y = second.ask(op=op, case=name, reps=reps, **({"device": dev} if second is ours else {}))
                    xa, xb = (x, y) if first is ours else (y, x)
                    ta += xa["times"]
                    tb += xb["times"]
                    acc = xa.get("accept", acc)
                ma, mb = 1e3 * statistics.median(ta), 1e3 * statistics.median(tb)
                extra = f"  (acceptance in the timed iterations {acc:.2f})" if acc is not None else ""
                print(f"  {op:9s}: ours median {ma:7.3f} ms, peer {mb:7.3f} ms, speedup {mb / ma:.2f}x "
                      f"({len(ta)} calls each){extra}")
                results.append((f"{op}_{name}{tag}", ma, mb))
    finally:
        ours.close()
        peer.close()
    for nm, ma, mb in results:
        print(f"RESULT {nm}: ours {ma:.3f} ms{on}, peer {mb:.3f} ms{' (cpu)' if on else ''}, speedup {mb / ma:.2f}x")


if __name__ == "__main__":
    main()
