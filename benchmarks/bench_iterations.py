"""Benchmark: two Levenberg–Marquardt iterations against their floors (issue 19, item 2), CPU time.

Both cases print the parts of one iteration, the whole iteration, the floor measured in the same run
and the ratio iteration / floor, for the installed code ("after") and for the code before these kernels
("before": ``git show <--before>:<file>``, default 93e3768, loaded as a separate module and run on the
same model).
Every number is the median over ``--repeats`` repeats of the CPU time (``time.process_time``) of one
call; within a repeat the items are interleaved (before, after, floor), so a drift of the machine's
speed shows in all of them.

[B1] NARX iteration: the linear-motor PGNN of ``conf/model/pgnn.yaml`` (forward, 16 tanh neurons, 84
parameters) on ``--rows`` (120,000) training rows of the ``bench_lm.py`` record, θ after
``--fit-iter`` LM steps.  The iteration is what LM does per accepted step with
``pipeline.identify.narx.criterion``: the residual at θ, then ``jacobian.normal_equations(θ, r)``
(JᵀJ and Jᵀr; the hidden activations of that residual reused).  Floor: ``scipy.linalg.blas.dsyrk``
of the criterion's 120,000 × 84 J (in memory; numpy's ``J.T @ J``, also syrk, is printed too and the
floor is the faster of the two).

[K] SK inner iteration of the PGNN with shared AR dynamics (``conf/experiment/k_two_mass.yaml``:
model ``pgnn_shared_ar``, MLP 5-10-10-1 tanh, 180 parameters, orthogonal regulariser λ = 1) on the
nine [K] training references (21,167 samples), after ``--sk-iter`` SK iterations of ``--lm-iter`` LM
steps; the problem is the next SK step's variable projection (``pipeline.identify.sk._varpro_step``,
its closures captured by replacing ``levenberg_marquardt`` for one call).  The iteration: the residual
at φ, then the normal equations at φ (a new φ at every repeat, so nothing is reused from the previous
one).  Floor: syrk of the filtered Jacobian W ∂g/∂φ (21,167 × 180; the fastest of scipy dsyrk in
either layout and numpy's ``WJ.T @ WJ``) plus one filtering pass of its 180 columns by 1/B (the
faster of ``filter_segments`` — scipy's lfilter, the path before — and a numba pass with lfilter's
arithmetic on the rows, the kernel of the new code without the Jacobian).

The numerics are checked too: B1 residual, JᵀJ and Jᵀr against the code before (equal to the bit);
K residual (to the bit) and JᵀJ, Jᵀr, J (relative difference).

Usage: ``OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_iterations.py [--case b1|k|both]
[--repeats 21] [--no-before] [--json out.json]``.  Numbers depend on the machine's load; run it alone.
"""
from __future__ import annotations

import argparse
import atexit
import copy
import importlib.util
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
import warnings
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
import yaml  # noqa: E402
from scipy.linalg.blas import dsyrk  # noqa: E402

from pipeline.identify import narx, sk  # noqa: E402
from pipeline.models import activations  # noqa: E402
from pipeline.models.pgnn import PGNN  # noqa: E402
from pipeline.models.physics_maps import RigidBodyForward  # noqa: E402
from pipeline.models.rational import filter_segments  # noqa: E402
from pipeline.models.shared_ar import _lfilter_coefficients, _lfilter_step  # noqa: E402


# ----------------------------------------------------------------------------- helpers
def cpu_ms(fn) -> float:
    """CPU time of one call ``fn()`` [ms]."""
    t0 = time.process_time()
    fn()
    return (time.process_time() - t0) * 1e3


def head_module(path: str, name: str, rev: str):
    """The version of ``path`` at git revision ``rev`` as a module ``name`` (its imports resolve to the
    installed package)."""
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:{path}"], capture_output=True, text=True,
                         check=True).stdout
    d = Path(tempfile.mkdtemp(prefix="bench_iterations_"))
    atexit.register(shutil.rmtree, d, ignore_errors=True)
    f = d / f"{name}.py"
    f.write_text(src)
    spec = importlib.util.spec_from_file_location(name, f)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod                              # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def timed(fns: dict, repeats: int) -> dict:
    """Median CPU ms of every item, the items interleaved in every repeat (after one warm-up).  An item
    is ``fn()`` or ``fn(i)`` (:func:`per_repeat`, i = the repeat), with an untimed ``fn.setup(i)`` first
    if it has one (e.g. the residual LM evaluates before the normal equations)."""
    def call(f, i):
        if hasattr(f, "setup"):
            f.setup(i)
        return cpu_ms(lambda: f(i)) if getattr(f, "takes_repeat", False) else cpu_ms(f)
    for f in fns.values():
        call(f, 0)
    times = {k: [] for k in fns}
    for i in range(repeats):
        for k, f in fns.items():
            times[k].append(call(f, i))
    return {k: float(np.median(v)) for k, v in times.items()}


def per_repeat(fn, setup=None):
    fn.takes_repeat = True
    if setup is not None:
        fn.setup = setup
    return fn


def rel(a, b) -> float:
    a, b = np.asarray(a), np.asarray(b)
    return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))


def show(title: str, rows: list[tuple[str, float | None, float | None]]) -> None:
    print(title)
    print(f"  {'':58s} {'before':>9s} {'after':>9s}")
    for name, b, a in rows:
        fb = f"{b:9.2f}" if isinstance(b, float) else f"{'':9s}"
        fa = f"{a:9.2f}" if isinstance(a, float) else f"{'':9s}"
        print(f"  {name:58s} {fb} {fa}")


# ----------------------------------------------------------------------------- [B1]
def b1_problem(rows: int, fit_iter: int):
    """The linear-motor PGNN (conf/model/pgnn.yaml) after ``fit_iter`` LM steps and the pieces of
    its criterion, built as ``identify_pgnn`` builds them."""
    from bench_b1 import motor_data
    m = PGNN(2, 1, 0, structure="forward", physics=RigidBodyForward(1e-3), hidden=(16,),
             input_transform="raw", out_init="mirrored", out_init_scale=1.0)
    _, y, u = motor_data(round((rows + m.n_a) / 0.8))           # 80 % of the record: `rows` rows
    fit = narx.identify_pgnn(m, y, u, n_restarts=1, val_fraction=0.2, max_iter=fit_iter, ftol=0.0, gtol=0.0)
    ty, tu, _, _ = narx._split_tail(y, u, 0.2)
    train = narx.build_regression(m, ty, tu)
    target = torch.as_tensor(train.target)
    sigma = float(target.std())
    prep = m.prepare(torch.as_tensor(train.phi))
    R = torch.as_tensor(narx.regularizer_sqrt(0.01, m.physics.n_params))     # identify_pgnn's lam
    return m, prep, target, sigma, torch.as_tensor(fit.theta_phy_star), R, m.parameter_vector()


def bench_b1(args) -> dict:
    m, prep, target, sigma, ts, R, theta = b1_problem(args.rows, args.fit_iter)
    M, P = len(prep), m.n_params
    res, jac = narx.criterion(m, prep, target, sigma, ts, R)
    J = jac(theta)[:M].numpy().copy()                    # the criterion's J, [M, P] C order
    JT = J.T                                             # F order: syrk 'N' gives JᵀJ, no copy

    def iteration(res, jac):
        def run():
            r = res(theta)
            jac.normal_equations(theta, r)
        return run

    fns = {}
    if not args.no_before:
        pg_old = head_module("pipeline/models/pgnn.py", "pgnn_before", args.before)
        narx_old = head_module("pipeline/identify/narx.py", "narx_before", args.before)
        m_old = pg_old.PGNN(2, 1, 0, structure="forward", physics=pg_old.RigidBodyForward(1e-3), hidden=(16,),
                            input_transform="raw", out_init="mirrored", out_init_scale=1.0)
        m_old.load_state_dict(m.state_dict())
        prep_old = pg_old.Prepared(prep.offset, prep.T, prep.x)
        res_o, jac_o = narx_old.criterion(m_old, prep_old, target, sigma, ts, R)
        r_o = res_o(theta)
        A_o, g_o = jac_o.normal_equations(theta, r_o)
        r_n = res(theta)
        A_n, g_n = jac.normal_equations(theta, r_n)
        eq = {"residual": torch.equal(r_n, r_o), "JᵀJ": torch.equal(A_n, A_o), "Jᵀr": torch.equal(g_n, g_o)}
        print("B1 numerics, installed vs before: " + ", ".join(
            f"{k} {'equal to the bit' if v else 'differs'}" for k, v in eq.items())
            + ("" if all(eq.values()) else f" (max rel JᵀJ {rel(A_n, A_o):.1e}, Jᵀr {rel(g_n, g_o):.1e})"))

        def ne_old():                                    # as LM calls it: after the residual at θ
            jac_o.normal_equations(theta, r_o)
        ne_old.setup = lambda i: res_o(theta)
        fns.update({"before: residual": lambda: res_o(theta), "before: normal equations": ne_old,
                    "before: iteration": iteration(res_o, jac_o)})
    r_n = res(theta)

    def ne_new():                                        # as LM calls it: after the residual at θ
        jac.normal_equations(theta, r_n)
    ne_new.setup = lambda i: res(theta)
    _, ((W1, b1), _) = m._unflatten(theta)
    z = torch.addmm(b1, prep.x, W1.T)                    # the pre-activations of the hidden layer
    h = torch.empty_like(z)
    fns.update({"after: residual": lambda: res(theta), "after: normal equations": ne_new,
                "after: iteration": iteration(res, jac),
                "part: tanh of the hidden layer, torch": lambda: torch.tanh(z, out=h),
                "part: tanh of the hidden layer, numpy": lambda: np.tanh(z.numpy(), out=h.numpy()),
                "floor: scipy dsyrk of J": lambda: dsyrk(1.0, JT, trans=0, lower=1),
                "floor: numpy J.T @ J": lambda: J.T @ J})
    t = timed(fns, args.repeats)
    floor = min(t["floor: scipy dsyrk of J"], t["floor: numpy J.T @ J"])
    g = lambda k: t.get(k)                               # noqa: E731
    rows = [("residual (prediction, hidden activations kept)", g("before: residual"), g("after: residual")),
            (f"  tanh of the {M} x {m.hidden[0]} hidden layer, numpy's", None,
             t["part: tanh of the hidden layer, numpy"]),
            (f"  tanh of the same, torch's (the model's here: {activations.IMPLEMENTATION})", None,
             t["part: tanh of the hidden layer, torch"]),
            ("normal equations JᵀJ, Jᵀr (Jacobian rows, syrk, gemv)", g("before: normal equations"),
             g("after: normal equations")),
            ("iteration = residual + normal equations", g("before: iteration"), g("after: iteration")),
            (f"floor: scipy dsyrk of the {M} x {P} J", None, t["floor: scipy dsyrk of J"]),
            ("floor: numpy J.T @ J (syrk)", None, t["floor: numpy J.T @ J"])]
    show(f"[B1] NARX LM iteration, J {M} x {P}; CPU ms, median of {args.repeats}", rows)
    out = {"rows": M, "params": P, **{f"{k} [ms]": v for k, v in t.items()}, "floor [ms]": floor,
           "ratio after": t["after: iteration"] / floor,
           "ratio after / scipy dsyrk": t["after: iteration"] / t["floor: scipy dsyrk of J"]}
    line = (f"  floor (the faster syrk) {floor:.2f} ms; ratio iteration / floor: after {out['ratio after']:.2f}x")
    if "before: iteration" in t:
        out["ratio before"] = t["before: iteration"] / floor
        out["ratio before / scipy dsyrk"] = t["before: iteration"] / t["floor: scipy dsyrk of J"]
        line += f", before {out['ratio before']:.2f}x"
    line += f" (against scipy's dsyrk alone: after {out['ratio after / scipy dsyrk']:.2f}x"
    if "ratio before / scipy dsyrk" in out:
        line += f", before {out['ratio before / scipy dsyrk']:.2f}x"
    print(line + "; target <= 1.3x)")
    return out


# ----------------------------------------------------------------------------- [K]
@numba.njit(cache=True)
def _filter_rows(X, b, a, bounds, out):
    """One filtering pass of the columns of X [N, m] (C order) by lfilter's arithmetic, per segment."""
    Z = np.zeros((max(b.shape[0] - 1, 1), X.shape[1]))
    for s in range(bounds.shape[0]):
        Z[:] = 0.0
        for k in range(bounds[s, 0], bounds[s, 1]):
            _lfilter_step(X[k], out[k], Z, b, a)


def k_problem(sk_iter: int, lm_iter: int, seed: int = 0):
    """The k_two_mass PGNN (conf/model/pgnn_shared_ar.yaml) after ``sk_iter`` SK iterations and the
    next SK step's weighted problem (as ``sk_iterations`` builds it)."""
    from bench_k import training_data
    from stages.train.sk_oe import build_model
    from pipeline import schema
    from pipeline.models import shared_ar
    from stages.train import Orthogonal
    # the option's parameter class holds the defaults, its YAML only what differs
    cfg = {**schema.defaults(shared_ar.Params), **yaml.safe_load((ROOT / "conf/model/pgnn_shared_ar.yaml").read_text())}
    lam = float({**schema.defaults(Orthogonal),
                 **yaml.safe_load((ROOT / "conf/regularizer/orthogonal.yaml").read_text())}["lam"])
    plant, rs, fs = training_data()
    model = build_model(cfg, plant.Ts, rs, seed)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", sk.SKNotConvergedWarning)
        model = sk.sk_iterations(model, rs, fs, max_iter=sk_iter, tol=0.0, regularizer="orthogonal", lam=lam,
                                 lm_max_iter=lm_iter, lm_ftol=1e-4, lm_gtol=1e-10).model
    data = sk.prepare_data(model, rs, fs)
    den, seg = model.denominator(), data["segments"]
    WM = filter_segments(data["M"], [1.0], den, seg)
    Wf = filter_segments(data["f"], [1.0], den, seg)
    sub = sk.model_subspace(WM, column_scale=True, names=data["names"], rank_deficient="truncate")
    return model, data, sub, Wf, den, lam


def varpro_closures(mod, model, data, sub, Wf, den, lam) -> tuple:
    """(residual, jacobian, φ) of ``mod._varpro_step`` for this problem (its LM replaced for one call)."""
    cap = {}

    class _Captured(Exception):
        pass

    def capture(residual, theta0, jacobian=None, **kw):
        cap.update(residual=residual, jacobian=jacobian, phi=theta0.clone())
        raise _Captured

    lm = mod.levenberg_marquardt
    mod.levenberg_marquardt = capture
    try:
        mod._varpro_step(model, data, sub, Wf, den, lam, {})
    except _Captured:
        pass
    finally:
        mod.levenberg_marquardt = lm
    return cap["residual"], cap["jacobian"], cap["phi"]


def bench_k(args) -> dict:
    model, data, sub, Wf, den, lam = k_problem(args.sk_iter, args.lm_iter)
    inp, seg = data["inputs"], data["segments"]
    res, jac, phi0 = varpro_closures(sk, model, data, sub, Wf, den, lam)
    # a new φ at every call (the closures cache the filtered Jacobian per φ): one list per timed item
    def phi_list(item: int) -> list[torch.Tensor]:
        return [phi0 * (1.0 + 1e-9 * (item * (args.repeats + 1) + i + 1)) for i in range(args.repeats + 1)]
    _, Jg = model.g_and_jacobian(inp, phi0)
    Jg_c = np.ascontiguousarray(Jg.numpy())              # [N, n_φ] C order (rows in time)
    WJ_F = filter_segments(Jg.numpy(), [1.0], den, seg)   # F order, as the code before held it
    WJ_C = np.ascontiguousarray(WJ_F)
    b, a = _lfilter_coefficients([1.0], den)
    bounds = np.array(seg.bounds, dtype=np.int64)
    out_rows = np.empty_like(Jg_c)
    N, n_phi = WJ_C.shape
    U1 = sub.U1

    def iteration(res, jac, phis):
        @per_repeat
        def run(i=0):
            p = phis[i % len(phis)]
            r = res(p)
            jac.normal_equations(p, r)
        return run

    fns = {}
    if not args.no_before:
        sk_old = head_module("pipeline/identify/sk.py", "sk_before", args.before)
        res_o, jac_o, _ = varpro_closures(sk_old, model, data, sub, Wf, den, lam)
        r_o, r_n = res_o(phi0), res(phi0)
        A_o, g_o = jac_o.normal_equations(phi0, r_o)
        A_n, g_n = jac.normal_equations(phi0, r_n)
        print(f"K numerics, installed vs before: residual "
              f"{'equal to the bit' if torch.equal(r_n, r_o) else f'max rel {rel(r_n, r_o):.1e}'}; "
              f"JᵀJ max rel {rel(A_n, A_o):.1e}, Jᵀr max rel {rel(g_n, g_o):.1e}, J ‖ΔJ‖/‖J‖ "
              f"{float(torch.linalg.norm(jac(phi0) - jac_o(phi0)) / torch.linalg.norm(jac_o(phi0))):.1e} "
              "(∂g/∂φ by closed-form backpropagation in numba instead of torch autograd: other sums)")

        phis_ne_old = phi_list(1)
        r_prev = {}

        def ne_old(i=0):
            jac_o.normal_equations(phis_ne_old[i % len(phis_ne_old)], r_prev["r"])
        per_repeat(ne_old, lambda i: r_prev.update(r=res_o(phis_ne_old[i % len(phis_ne_old)])))
        fns.update({
            "before: residual": lambda: res_o(phi0),
            "before: normal equations": ne_old,
            "before: iteration": iteration(res_o, jac_o, phi_list(2)),
            "before, part: jacobian of g (per_sample_jacobian)": lambda: model.g_and_jacobian(inp, phi0),
            "before, part: 1/B filtering (filter_segments)": lambda: filter_segments(Jg.numpy(), [1.0], den, seg),
            "before, part: projection U1ᵀ WJ": lambda: U1.T @ WJ_F,
            "before, part: JᵀJ (numpy WJ.T @ WJ)": lambda: WJ_F.T @ WJ_F})
    r_n = res(phi0)
    acts = model.g_forward(inp, phi0)[1]
    U1c, r1 = np.ascontiguousarray(U1), r_n.numpy()[:N]

    phis_ne_new = phi_list(3)
    r_last = {}

    def ne_new(i=0):                                     # as LM calls it: after the residual at that φ
        jac.normal_equations(phis_ne_new[i % len(phis_ne_new)], r_last["r"])
    per_repeat(ne_new, lambda i: r_last.update(r=res(phis_ne_new[i % len(phis_ne_new)])))
    # the geodesic acceleration's J v and Jᵀ w (lm.py), after the normal equations at that φ, as LM calls
    # them; "explicit": the full J formed first (the code before 2026-12-03), "after": J never formed
    phis_geo = phi_list(5)
    v_geo = torch.from_numpy(np.random.default_rng(1).standard_normal(n_phi))
    w_geo = torch.from_numpy(np.random.default_rng(2).standard_normal(r_n.numel()))

    def geo_setup(i):
        p = phis_geo[i % len(phis_geo)]
        jac.normal_equations(p, res(p))

    def geo_after(i=0):
        p = phis_geo[i % len(phis_geo)]
        jac.jvp(p, v_geo), jac.vjp(p, w_geo)

    def geo_explicit(i=0):
        J = jac(phis_geo[i % len(phis_geo)])
        J @ v_geo, J.T @ w_geo
    per_repeat(geo_after, geo_setup)
    per_repeat(geo_explicit, geo_setup)
    fns.update({
        "after: residual": lambda: res(phi0),
        "after: normal equations": ne_new,
        "after, geodesic: J v and Jᵀ w, J not formed": geo_after,
        "explicit, geodesic: J formed, J v and Jᵀ w": geo_explicit,
        "after: iteration": iteration(res, jac, phi_list(4)),
        "after, part: g forward (activations kept)": lambda: model.g_forward(inp, phi0),
        "after, part: W ∂g/∂φ stored (rare columns)": lambda: model.filtered_jacobian(
            inp, phi0, [1.0], den, seg, acts),
        "after, part: W ∂g/∂φ reduced in blocks (G, C, WJᵀr)": lambda: model.filtered_jacobian_gram(
            inp, phi0, [1.0], den, seg, U1c, r1, acts),
        "floor: scipy dsyrk of WJ (F order, 'T')": lambda: dsyrk(1.0, WJ_F, trans=1, lower=1),
        "floor: scipy dsyrk of WJ (C order, 'N')": lambda: dsyrk(1.0, WJ_C.T, trans=0, lower=1),
        "floor: numpy WJ.T @ WJ": lambda: WJ_F.T @ WJ_F,
        "floor: filtering pass, filter_segments (lfilter)": lambda: filter_segments(Jg.numpy(), [1.0], den, seg),
        "floor: filtering pass, numba rows (lfilter arithmetic)": lambda: _filter_rows(Jg_c, b, a, bounds,
                                                                                        out_rows)})
    t = timed(fns, args.repeats)
    syrk = min(t["floor: scipy dsyrk of WJ (F order, 'T')"], t["floor: scipy dsyrk of WJ (C order, 'N')"],
               t["floor: numpy WJ.T @ WJ"])
    filt = min(t["floor: filtering pass, filter_segments (lfilter)"],
               t["floor: filtering pass, numba rows (lfilter arithmetic)"])
    floor = syrk + filt
    g = lambda k: t.get(k)                               # noqa: E731
    rows = [("residual (g, 1/B filtering of g, projection)", g("before: residual"), g("after: residual")),
            ("normal equations (W ∂g/∂φ, projection, JᵀJ, Jᵀr)", g("before: normal equations"),
             g("after: normal equations")),
            ("  jacobian of g (per_sample_jacobian)", g("before, part: jacobian of g (per_sample_jacobian)"), None),
            ("  1/B filtering, column by column (filter_segments)",
             g("before, part: 1/B filtering (filter_segments)"), None),
            ("  projection U1ᵀ WJ", g("before, part: projection U1ᵀ WJ"), None),
            ("  JᵀJ (numpy WJ.T @ WJ)", g("before, part: JᵀJ (numpy WJ.T @ WJ)"), None),
            ("  g forward, activations kept (in the residual)", None,
             g("after, part: g forward (activations kept)")),
            ("  W ∂g/∂φ + syrk + U1ᵀWJ + WJᵀr in blocks (one kernel)", None,
             g("after, part: W ∂g/∂φ reduced in blocks (G, C, WJᵀr)")),
            ("  W ∂g/∂φ stored whole (rare columns only)", None,
             g("after, part: W ∂g/∂φ stored (rare columns)")),
            ("iteration = residual + normal equations", g("before: iteration"), g("after: iteration")),
            ("geodesic step's J v, Jᵀ w (J formed | J not formed)", g("explicit, geodesic: J formed, J v and Jᵀ w"),
             g("after, geodesic: J v and Jᵀ w, J not formed")),
            ("floor: syrk of WJ, scipy dsyrk (F order, 'T')", None, t["floor: scipy dsyrk of WJ (F order, 'T')"]),
            ("floor: syrk of WJ, scipy dsyrk (C order, 'N')", None, t["floor: scipy dsyrk of WJ (C order, 'N')"]),
            ("floor: syrk of WJ, numpy WJ.T @ WJ", None, t["floor: numpy WJ.T @ WJ"]),
            ("floor: filtering pass of 180 columns, filter_segments", None,
             t["floor: filtering pass, filter_segments (lfilter)"]),
            ("floor: filtering pass of 180 columns, numba rows", None,
             t["floor: filtering pass, numba rows (lfilter arithmetic)"])]
    show(f"[K] SK inner LM iteration (PGNN, shared AR), N = {N}, n_φ = {n_phi}; CPU ms, median of "
         f"{args.repeats}", rows)
    out = {"N": N, "n_phi": n_phi, **{f"{k} [ms]": v for k, v in t.items()}, "floor syrk [ms]": syrk,
           "floor filtering [ms]": filt, "floor [ms]": floor, "ratio after": t["after: iteration"] / floor}
    line = (f"  floor = syrk {syrk:.2f} + filtering {filt:.2f} = {floor:.2f} ms; ratio iteration / floor: "
            f"after {out['ratio after']:.2f}x")
    if "before: iteration" in t:
        out["ratio before"] = t["before: iteration"] / floor
        line += f", before {out['ratio before']:.2f}x"
    print(line + " (target <= 1.5x)")
    if args.gram_blocks:
        # the kernel's rows per syrk (shared_ar.filtered_jacobian_gram's block): OpenBLAS's syrk on this
        # CPU was ~20 % slower at 256 and 512 rows than at any other size from 96 to 1536 (issue 19)
        tb = timed({b: (lambda b=b: model.filtered_jacobian_gram(inp, phi0, [1.0], den, seg, U1c, r1, acts,
                                                                  block=b)) for b in args.gram_blocks},
                   args.repeats)
        print("  one kernel by rows per block: " + ", ".join(f"{b}: {v:.2f}" for b, v in tb.items()) + " ms")
        out["gram ms by block"] = tb
    out["oe_check"] = bench_oe_check(args, model, data, den, lam)
    return out


class _GenericJacobian:
    """Mixin: the model on the generic path (torch's per-sample ∂g/∂φ, each column filtered by lfilter)."""
    closed_form_jacobian = False


def bench_oe_check(args, model, data, den, lam) -> dict:
    """The K3 check's Jacobian (``sk.output_error_problem``, J_OE + λR over θ and φ, R frozen at the
    weighting 1/B): the generic path (the code before 3e1c67b) against the closed form from the residual's
    activations, at the same x (residual first, as LM calls them)."""
    sub = sk._frozen_subspace(model, data, den, column_scale=True, rank_rtol=None)
    generic = copy.deepcopy(model)
    generic.__class__ = type("Generic" + type(model).__name__, (_GenericJacobian, type(model)), {})
    res_c, jac_c, x0 = sk.output_error_problem(model, data, lam=lam, sub=sub, weighting=den)
    res_g, jac_g, _ = sk.output_error_problem(generic, data, lam=lam, sub=sub, weighting=den)
    xs = [x0 * (1.0 + 1e-9 * (i + 1)) for i in range(args.repeats + 1)]
    J_c, J_g = jac_c(x0).numpy(), jac_g(x0).numpy()
    diff = float(np.max(np.abs(J_c - J_g) / np.abs(J_g).max(axis=0)))

    def it(res, jac):
        def run(i=0):
            jac(xs[i % len(xs)])
        return per_repeat(run, lambda i: res(xs[i % len(xs)]))
    t = timed({"generic": it(res_g, jac_g), "closed": it(res_c, jac_c),
               "gram": lambda: J_c.T @ J_c}, args.repeats)
    show(f"[K] K3 check: Jacobian of J_OE + λR over (θ, φ), {J_c.shape[0]} × {J_c.shape[1]}; CPU ms, median of "
         f"{args.repeats}", [("Jacobian (generic: per-sample ∂g/∂φ, lfilter per column | closed form)",
                              t["generic"], t["closed"]),
                             ("JᵀJ of it (numpy, syrk), for scale", None, t["gram"])])
    print(f"  closed form vs generic: max |ΔJ| / column max {diff:.1e} (equal to rounding); "
          f"{t['generic'] / t['closed']:.1f}x faster")
    return {"generic [ms]": t["generic"], "closed [ms]": t["closed"], "gram [ms]": t["gram"], "max_rel_diff": diff}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--case", choices=("b1", "k", "both"), default="both")
    ap.add_argument("--repeats", type=int, default=21)
    ap.add_argument("--rows", type=int, default=120_000, help="B1 training rows")
    ap.add_argument("--fit-iter", type=int, default=3, help="B1: LM steps before timing")
    ap.add_argument("--sk-iter", type=int, default=2, help="K: SK iterations before timing")
    ap.add_argument("--lm-iter", type=int, default=10, help="K: LM steps per SK iteration before timing")
    ap.add_argument("--before", type=str, default="93e3768",
                    help="git revision of the code before these kernels (default 93e3768)")
    ap.add_argument("--no-before", action="store_true", help="skip the code before")
    ap.add_argument("--gram-blocks", type=int, nargs="*", default=[128, 192, 240, 256, 320, 512, 1024],
                    help="K: rows per block of the fused kernel to time (none: skip)")
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args(argv)
    sys.stdout.reconfigure(line_buffering=True)
    torch.set_num_threads(1)
    out = {}
    if args.case in ("b1", "both"):
        out["b1"] = bench_b1(args)
    if args.case in ("k", "both"):
        out["k"] = bench_k(args)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2))
    return out


if __name__ == "__main__":
    main()
