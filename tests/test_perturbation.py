"""The perturbation check (issue 19): the comparison of two summaries, and the LM hook."""
import os
import subprocess
import sys

import pandas as pd
import pytest

from pipeline.perturbation import compare


def _summary(values, holds="True"):
    return pd.DataFrame({"experiment": ["e1", "e1", "e2", "e2"], "claim": ["C1", "", "", ""],
                         "variant": ["a", "a", "b", "b"],
                         "metric": ["mae", "train/seconds", "cost", "theta/M"],
                         "value": values, "paper_value": [None] * 4, "claim_holds": [holds, None, None, None]})


def test_compare_reports_the_largest_change_per_experiment_and_skips_timings():
    ref = _summary([1.0, 10.0, 2.0, 5.0])
    per = _summary([1.0, 99.0, 2.1, 5.0], holds="False")
    keys, summ = compare(ref, per, rtol=0.02)
    assert "train/seconds" not in set(keys["metric"])              # a timing is not a result
    s = summ.set_index("experiment")
    assert s.loc["e1", "max_rel_change"] == 0.0 and s.loc["e1", "verdicts_changed"] == 1
    assert s.loc["e2", "max_rel_change"] == pytest.approx(0.1 / 2.1)
    assert s.loc["e2", "worst_key"] == "b|cost" and s.loc["e2", "n_above_rtol"] == 1
    # a key on one side only is counted, not compared
    keys, summ = compare(ref, per.iloc[:3], rtol=0.02)
    s = summ.set_index("experiment")
    assert s.loc["e2", "keys_on_one_side"] == 1 and s.loc["e2", "max_rel_change"] == pytest.approx(0.1 / 2.1)


def test_a_claim_verdict_changes_only_when_the_claim_does_not_one_of_its_rows():
    """A claim holds when every one of its rows holds: a row that flips while another row of the claim
    fails on both sides changes a claim row, not the claim's verdict."""
    def side(first):
        return pd.DataFrame({"experiment": "b2", "claim": ["B2a", "B2a", "B2b"], "variant": ["n1=20", "n1=8", "x"],
                             "metric": ["eps", "eps", "m"], "value": [1.0, 2.0, 3.0], "paper_value": None,
                             "claim_holds": [first, "False", "True"]})
    s = compare(side("True"), side("False"), rtol=0.02)[1].iloc[0]
    assert s["verdicts_changed"] == 0 and s["claim_rows_changed"] == 1
    flipped = side("True").assign(claim_holds=["True", "True", "True"])
    s = compare(flipped, side("True"), rtol=0.02)[1].iloc[0]
    assert s["verdicts_changed"] == 1 and s["claim_rows_changed"] == 1


def test_a_tiny_value_that_moves_is_ill_determined_not_moved():
    """Against the floor 1e-3 x the largest value of its metric for its model in its experiment:
    1e-9 -> 2e-9 beside 20 moves 50 % of itself, 5e-11 of the floor: ill-determined (counted,
    spread kept), not moved; 1.0 -> 1.1 of another model in the same metric still moves."""
    def table(v):
        return pd.DataFrame({"experiment": ["k"] * 3, "claim": [""] * 3, "variant": ["pgnn/ref1", "pgnn/ref2", "phys"],
                             "metric": ["sq_norm2"] * 3, "value": v, "paper_value": [None] * 3,
                             "claim_holds": [None] * 3})
    keys, summ = compare(table([20.0, 1e-9, 1.0]), table([20.0, 2e-9, 1.1]), rtol=0.02)
    k = keys.set_index("variant")
    assert k.loc["pgnn/ref2", "ill_determined"] and k.loc["pgnn/ref2", "rel_change"] == pytest.approx(1e-9 / 0.02)
    assert not k.loc["phys", "ill_determined"] and k.loc["phys", "rel_change"] == pytest.approx(0.1 / 1.1)
    s = summ.iloc[0]
    assert s["n_above_rtol"] == 1 and s["n_ill_determined"] == 1


def test_a_fit_converged_on_both_sides_in_another_minimum_is_ill_determined_a_capped_one_moved():
    """Two fits whose training cost moved by 50 %: the one that stopped on its tolerance on both sides
    (fit_stopped_on_cap 0) landed in another local minimum, its value is ill-determined (other minimum);
    the one that stopped on a cap on one side landed on a slope, its value moved; a fit without the
    flag row is not classified (moved)."""
    def side(cost, flag_b):
        rows = []
        for v, f in (("a", 0.0), ("b", flag_b), ("c", None)):
            rows += [(v, "fit_cost", cost)] + ([] if f is None else [(v, "fit_stopped_on_cap", f)]) + \
                [(f"{v}/R", "mae", cost * 10)]
        return pd.DataFrame({"experiment": "b2", "claim": "", "variant": [r[0] for r in rows],
                             "metric": [r[1] for r in rows], "value": [r[2] for r in rows],
                             "paper_value": None, "claim_holds": None})
    keys, summ = compare(side(1.0, 0.0), side(1.5, 1.0), rtol=0.02)
    k = keys.set_index(["variant", "metric"])
    assert k.loc[("a/R", "mae"), "category"] == "other_minimum" and k.loc[("a/R", "mae"), "ill_determined"]
    assert k.loc[("a", "fit_cost"), "category"] == "other_minimum"
    assert k.loc[("b/R", "mae"), "category"] == "moved" and not k.loc[("b/R", "mae"), "ill_determined"]
    assert k.loc[("c/R", "mae"), "category"] == "moved"
    assert k.loc[("b", "fit_stopped_on_cap"), "category"] == "moved"      # converged on one side only
    s = summ.iloc[0]
    assert s["n_other_minimum"] == 2 and s["n_above_rtol"] == 5 and s["fits_moved"] == "3 of 3"


def test_the_check_names_each_fit_that_stopped_on_its_cap_and_how_far_its_values_moved():
    """A fit flagged fit_stopped_on_cap = 1 in the reference gets a line of its own: both training
    costs, whether it stopped on its cap again, and the largest change of its values."""
    from pipeline.perturbation import capped_fits, markdown

    def side(cost, flag, mae):
        return pd.DataFrame({"experiment": "b2", "claim": "", "variant": ["n1=24", "n1=24", "n1=24/R", "n1=8", "n1=8"],
                             "metric": ["fit_cost", "fit_stopped_on_cap", "mae", "fit_cost", "fit_stopped_on_cap"],
                             "value": [cost, flag, mae, 1.0, 0.0], "paper_value": None, "claim_holds": None})
    keys, summ = compare(side(3e-9, 1.0, 2.0), side(2.4e-9, 0.0, 2.1), rtol=0.01)
    c = capped_fits(keys)
    assert list(c["fit"]) == ["n1=24"] and not c["still_capped"].iloc[0]
    assert c["max_value_change"].iloc[0] == pytest.approx(0.1 / 2.1) and c["n_values"].iloc[0] == 1
    md = markdown(summ, 0.01, "tighten", "T=10", keys)
    assert "`b2` `n1=24`: training cost 3e-09 → 2.4e-09, its 1 values move by up to 4.76%" in md


@pytest.mark.slow      # two subprocesses per case (~8 s); the tightening test below covers the hook path
@pytest.mark.parametrize("eps", ["0", "1e-13"])
def test_perturbation_reaches_the_lm_and_a_converged_fit_stays(eps):
    # the same LM problem in a subprocess with PIPELINE_PERTURB: the perturbed fit differs from the
    # unperturbed one in the last digits only (a converged linear least-squares problem)
    code = ("import torch\nfrom pipeline.identify.lm import levenberg_marquardt as lm\n"
            "g = torch.Generator().manual_seed(0)\n"
            "A = torch.randn(50, 4, generator=g, dtype=torch.float64)\n"
            "b = torch.randn(50, generator=g, dtype=torch.float64)\n"
            "r = lm(lambda t: A @ t - b, torch.zeros(4, dtype=torch.float64), jacobian=lambda t: A)\n"
            "print(repr(r.theta.tolist()))\n")
    out = [eval(subprocess.run([sys.executable, "-c", code], env={**os.environ, "PIPELINE_PERTURB": e},
                               capture_output=True, text=True, check=True).stdout) for e in ("0", eps)]
    diff = max(abs(x - y) for x, y in zip(*out))
    if eps == "0":
        assert diff == 0.0
    else:
        assert 0.0 < diff < 1e-10


_FIT = """
import json, torch
from pipeline.identify.lm import levenberg_marquardt as lm
x = torch.linspace(-2, 2, 400, dtype=torch.float64)
y = torch.sin(2 * x) * torch.exp(-0.3 * x ** 2) + 0.3 * x
th0 = torch.randn(25, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
net = lambda th: torch.tanh(x[:, None] * th[:8] + th[8:16]) @ th[16:24] + th[24]
A = torch.randn(50, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
b = torch.randn(50, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
loose = lm(lambda t: net(t) - y, th0, ftol=0.2, gtol=0.0, max_iter=3000)       # deliberately unconverged
tight = lm(lambda t: A @ t - b, torch.zeros(4, dtype=torch.float64), jacobian=lambda t: A, ftol=1e-10)
print(json.dumps({"loose": loose.cost, "converged": tight.cost, "n_loose": loose.n_iter}))
"""


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_tightening_check_flags_a_deliberately_unconverged_fit():
    """The check's logic on two fits: tightening every tolerance 10x (PIPELINE_TIGHTEN) moves the
    cost of a fit stopped on a loose ftol by far more than the 1 % rtol, and leaves a converged
    least-squares fit where it was; compare() flags exactly the first."""
    import json
    runs = []
    for t in ("1", "10"):
        out = subprocess.run([sys.executable, "-c", _FIT], env={**os.environ, "PIPELINE_TIGHTEN": t},
                             capture_output=True, text=True, check=True).stdout
        runs.append(json.loads(out))
    assert runs[1]["n_loose"] > runs[0]["n_loose"]                  # the tolerance reached the LM

    def frame(r):
        return pd.DataFrame({"experiment": ["loose", "converged"], "claim": ["", ""], "variant": ["a", "a"],
                             "metric": ["cost", "cost"], "value": [r["loose"], r["converged"]],
                             "paper_value": [None, None], "claim_holds": [None, None]})
    _, summ = compare(frame(runs[0]), frame(runs[1]), rtol=0.01)
    s = summ.set_index("experiment")
    assert s.loc["loose", "n_above_rtol"] == 1 and s.loc["loose", "max_rel_change"] > 0.01
    assert s.loc["converged", "n_above_rtol"] == 0 and s.loc["converged", "max_rel_change"] < 1e-9


def test_report_shows_the_check_of_its_own_summary_only(tmp_path):
    """The report's check section comes from check-perturb.csv when check-perturb.json names this
    summary.csv's sha256 (the same table as check-perturb.md); a check of another summary is named
    stale, one written before the categories existed is named old."""
    import json
    from pipeline.perturbation import markdown, summary_digest
    from stages.report import _with_checks

    def table(v):
        return pd.DataFrame({"experiment": ["k", "k"], "claim": ["", ""], "variant": ["a/r1", "a/r2"],
                             "metric": ["m", "m"], "value": v, "paper_value": [None] * 2, "claim_holds": [None] * 2})
    (tmp_path / "summary.csv").write_text("experiment,claim,variant,metric,value\nk,,a,m,1\n")
    keys, summ = compare(table([1.0, 1e-9]), table([1.5, 2e-9]), rtol=0.02)
    keys.to_csv(tmp_path / "check-perturb.csv", index=False)
    digest = summary_digest(tmp_path / "summary.csv")
    (tmp_path / "check-perturb.json").write_text(json.dumps({"reference_sha256": digest, "setting": "P=1e-13",
                                                              "rtol": 0.02}))
    md = _with_checks("# Results\n\nhead\n\n## k\n\nsection\n", tmp_path)
    line = "| k | 2 | 0.333 | `a/r1|m` | 1 | 1 | 0 | 0 | 0 of 0 | 0 (0) | 0 |"
    assert line in md and md.index("Same numbers") < md.index("## k")
    assert line in markdown(summ, 0.02, "perturb", "P=1e-13")
    keys.drop(columns=["category"]).to_csv(tmp_path / "check-perturb.csv", index=False)
    assert "older version" in _with_checks("# Results\n\n## k\n", tmp_path)
    (tmp_path / "check-perturb.json").write_text(json.dumps({"reference_sha256": "0" * 64}))
    assert "(stale)" in _with_checks("# Results\n\n## k\n", tmp_path)


def test_values_of_equal_fits_are_ill_determined_and_of_moved_fits_moved():
    """A value row belongs to the fit whose variant is its longest '/'-prefix. Fit 'eq/direct' reached
    the same training cost on both sides (5e-5 relative < FIT_RTOL 1e-3): its tracking value that moved
    30 % is ill-determined (equal fits), not moved; fit 'eq/newton' landed 5 % higher: its value that
    moved counts as moved, and so does the fit's own cost row; 'eq/directly' is not under 'eq/direct'.
    Iteration counts are solver path, listed but not compared."""
    from pipeline.perturbation import FIT_METRIC, FIT_RTOL

    rows = [("eq/direct", FIT_METRIC, 1.0, 1.00005), ("eq/direct/v0.05", "mae", 1e-6, 1.3e-6),
            ("eq/newton", FIT_METRIC, 1.0, 1.05), ("eq/newton/v0.05", "mae", 1e-6, 1.3e-6),
            ("eq/directly/v0.05", "mae", 2e-6, 2.6e-6), ("eq/direct", "sk_iterations", 4.0, 9.0)]

    def table(i):
        return pd.DataFrame({"experiment": ["b1"] * len(rows), "claim": [""] * len(rows),
                             "variant": [r[0] for r in rows], "metric": [r[1] for r in rows],
                             "value": [r[i] for r in rows], "paper_value": [None] * len(rows),
                             "claim_holds": [None] * len(rows)})
    keys, summ = compare(table(2), table(3), rtol=0.02)
    k = keys.set_index(["variant", "metric"])["category"]
    assert 5e-5 < FIT_RTOL
    assert k[("eq/direct/v0.05", "mae")] == "equal_fit" and k[("eq/direct", FIT_METRIC)] == "same"
    assert k[("eq/newton/v0.05", "mae")] == "moved" and k[("eq/newton", FIT_METRIC)] == "moved"
    assert k[("eq/directly/v0.05", "mae")] == "moved" and k[("eq/direct", "sk_iterations")] == "solver_path"
    assert keys.set_index(["variant", "metric"]).loc[("eq/direct/v0.05", "mae"), "fit"] == "eq/direct"
    s = summ.iloc[0]
    got = (s["values"], s["n_above_rtol"], s["n_equal_fit"], s["fits_moved"], s["n_solver_path"])
    assert got == (5, 3, 1, "1 of 2", 1)
    assert s["max_rel_change"] == pytest.approx(0.3 / 1.3)


def test_the_tightening_check_runs_a_capped_fit_on_and_leaves_the_screening_budget(monkeypatch):
    """PIPELINE_CAP_FACTOR (make reproduce-check CHECK=tighten, CAPS; read into lm.CAP_FACTOR) multiplies the
    restarts' safety cap: the kept restart of a fit that stops on its cap runs on (up to twice as many LM
    steps), the screened ones keep their screening budget (the choice of the kept restart does not change)."""
    import torch

    from pipeline.identify import narx
    from pipeline.models.pgnn import PGNN
    from pipeline.models.physics_maps import LinearFeatures
    g = torch.Generator().manual_seed(0)
    phi = torch.randn(200, 2, generator=g, dtype=torch.float64)
    y = torch.tanh(3 * phi[:, 0]) * phi[:, 1]
    runs = {}
    for f in (1.0, 2.0):
        monkeypatch.setattr(narx, "CAP_FACTOR", f)
        m = PGNN(1, 1, physics=LinearFeatures(2), hidden=(4,), seed=0)
        out, best = narx.best_of_restarts(m, lambda th: m.predict(th, m.prepare(phi)) - y, None, 3, 0,
                                          max_iter=12, screen_iter=4, ftol=0.0, gtol=0.0)
        runs[f] = (out[best].n_iter, out[best].message, sorted(r.n_iter for r in out))
    assert runs[1.0] == (12, "max_iter", [4, 4, 12])
    assert 12 < runs[2.0][0] <= 24 and runs[2.0][2] == [4, 4, runs[2.0][0]]


def test_a_subset_check_replaces_its_experiments_and_keeps_the_others_while_their_rows_hold(tmp_path):
    """make reproduce-check EXPERIMENTS=<subset>: check-<check>.csv/.json keep the other experiments' rows of
    the previous check, each with the sha256 of the reference rows it compared; the report shows an
    experiment's check while its rows of summary.csv are unchanged and names it stale once they change."""
    import json
    from pipeline.perturbation import main
    from stages.report import _with_checks

    def table(rows):
        return pd.DataFrame([{"experiment": e, "claim": "", "variant": v, "metric": "m", "value": x,
                              "paper_value": None, "claim_holds": None} for e, v, x in rows])
    ref, out = tmp_path / "summary.csv", tmp_path / "out"
    table([("a", "p", 1.0), ("b", "q", 2.0)]).to_csv(ref, index=False)
    table([("a", "p", 1.5), ("b", "q", 2.0)]).to_csv(tmp_path / "full.csv", index=False)
    table([("b", "q", 2.2)]).to_csv(tmp_path / "only_b.csv", index=False)
    common = ["--out", str(out), "--check", "perturb", "--rtol", "0.02"]
    assert main([str(ref), str(tmp_path / "full.csv"), *common]) == 0
    assert main([str(ref), str(tmp_path / "only_b.csv"), *common]) == 0
    keys = pd.read_csv(out / "check-perturb.csv")
    got = dict(zip(keys["experiment"], keys["value_pert"]))
    assert got == {"a": 1.5, "b": 2.2}   # a kept from the full check, b replaced by the subset's
    meta = json.loads((out / "check-perturb.json").read_text())
    assert sorted(meta["experiments"]) == ["a", "b"]
    md = (out / "check-perturb.md").read_text()
    assert "| a | 1 | 0.333 |" in md and "| b | 1 | 0.0909 |" in md
    # the report over this summary shows both; once a's reference rows change, a is named stale
    for f in ("check-perturb.csv", "check-perturb.json"):
        (tmp_path / f).write_text((out / f).read_text())
    text = _with_checks("# R\n\n## k\n", tmp_path)
    assert "| a | 1 | 0.333 |" in text and "Stale" not in text
    table([("a", "p", 1.1), ("b", "q", 2.0)]).to_csv(ref, index=False)
    text = _with_checks("# R\n\n## k\n", tmp_path)
    assert "| a | 1 |" not in text and "| b | 1 | 0.0909 |" in text and "Stale" in text and ": a." in text
    # a subset rerun against the new reference drops a's rows (they compared other rows) but keeps naming it stale
    assert main([str(ref), str(tmp_path / "only_b.csv"), *common]) == 0
    assert set(pd.read_csv(out / "check-perturb.csv")["experiment"]) == {"b"}
    assert "Stale" in (out / "check-perturb.md").read_text() and ": a." in (out / "check-perturb.md").read_text()
    for f in ("check-perturb.csv", "check-perturb.json"):
        (tmp_path / f).write_text((out / f).read_text())
    text = _with_checks("# R\n\n## k\n", tmp_path)
    assert "Stale" in text and ": a." in text and "| b | 1 | 0.0909 |" in text
    # a rerun that lacks keys of the reference (one experiment file of several) is named partial
    table([("a", "p", 1.1), ("b", "q", 2.0), ("b", "q2", 3.0)]).to_csv(ref, index=False)
    assert main([str(ref), str(tmp_path / "only_b.csv"), *common]) == 0
    md = (out / "check-perturb.md").read_text()
    assert "Partial" in md and "b (1 keys)" in md
    # nothing in common: a clear error, the files untouched
    table([("c", "p", 1.0)]).to_csv(tmp_path / "only_c.csv", index=False)
    before = (out / "check-perturb.csv").read_text()
    with pytest.raises(SystemExit, match="no experiment in common"):
        main([str(ref), str(tmp_path / "only_c.csv"), *common])
    assert (out / "check-perturb.csv").read_text() == before


def test_the_report_of_an_empty_summary_has_no_experiment_digests(tmp_path):
    """A report without rows (report.experiments that never ran) writes a summary.csv without columns: its
    per-experiment digests are none (the check section must not fail on it)."""
    from pipeline.perturbation import experiment_digests
    pd.DataFrame().to_csv(tmp_path / "summary.csv", index=False)          # what the report stage writes then
    assert experiment_digests(tmp_path / "summary.csv") == {}
    (tmp_path / "summary.csv").write_text("")
    assert experiment_digests(tmp_path / "summary.csv") == {}


def test_rounding_residues_of_an_exact_identity_are_listed_not_compared_but_their_verdict_is():
    """[B2] B2e's lemma rows (relative difference of two exact expressions, the claim asks <= 1e-8): between two
    CPUs they went 6.9e-17 -> 9.2e-16 (measured, 2026-12-04); that is rounding, listed as solver path. A residue
    that breaks the identity still changes the claim's verdict."""
    def table(v, holds):
        return pd.DataFrame({"experiment": ["b2"] * 2, "claim": ["B2e"] * 2,
                             "variant": ["lemma_5_1/nmp", "lemma_5_1/mp"], "metric": ["relative_difference"] * 2,
                             "value": v, "paper_value": [None] * 2, "claim_holds": holds})
    keys, summ = compare(table([6.889e-17, 5.33e-16], [True, True]), table([9.25e-16, 5.10e-16], [True, True]),
                         rtol=0.02)
    assert set(keys["category"]) == {"solver_path"}
    s = summ.iloc[0]
    assert (s["values"], s["n_above_rtol"], s["n_solver_path"], s["verdicts_changed"]) == (0, 0, 2, 0)
    _, broken = compare(table([6.889e-17, 5.33e-16], [True, True]), table([3e-7, 5.10e-16], [False, True]),
                        rtol=0.02)
    assert broken.iloc[0]["verdicts_changed"] == 1


def test_a_ratio_of_two_fits_is_ill_determined_only_where_an_ill_determined_input_explains_its_move():
    """K2's ratio ``none_over_orthogonal`` of the two PGNNs' f_M spreads: the orthogonal spreads move 3 %
    at an equal training cost (ill-determined: equal fits), the unregularised ones 0.5 % (same). A ratio
    that moved 2.5 % (within 3 % + 0.5 %) is ill-determined like its input; one that moved 10 % (more
    than its inputs explain) and one whose inputs all held still count as moved."""
    from pipeline.perturbation import FIT_METRIC

    def table(ratio, so, sn=(0.04, 0.0402)):
        rows = [("pgnn_none", FIT_METRIC, 1.0, 1.0), ("pgnn_orthogonal", FIT_METRIC, 1.4, 1.40001),
                ("pgnn_none/r1", "spread_f_M", *sn), ("pgnn_orthogonal/r1", "spread_f_M", *so),
                ("none_over_orthogonal/min", "spread_f_M_ratio", *ratio)]
        return [pd.DataFrame({"experiment": "k", "claim": "K2", "variant": [r[0] for r in rows],
                              "metric": [r[1] for r in rows], "value": [r[i] for r in rows],
                              "paper_value": None, "claim_holds": "True"}) for i in (2, 3)]

    def category(*args):
        keys = compare(*table(*args), rtol=0.02)[0].set_index(["variant", "metric"])["category"]
        return keys[("pgnn_orthogonal/r1", "spread_f_M")], keys[("none_over_orthogonal/min", "spread_f_M_ratio")]

    assert category((800.0, 780.0), (5e-5, 5.15e-5)) == ("equal_fit", "equal_fit")
    assert category((800.0, 720.0), (5e-5, 5.15e-5)) == ("equal_fit", "moved")
    assert category((800.0, 780.0), (5e-5, 5.001e-5)) == ("same", "moved")
