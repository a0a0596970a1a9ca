"""The claim table (stages/report/claims.py, issue 21 item 4): every SPEC §8 claim is rows of data,
judged by one function; each test form decides on both sides of its threshold."""
import math
import re
from pathlib import Path

import pytest

from stages.report import claims
from stages.report._rows import row

ROOT = Path(__file__).resolve().parent.parent


def _judge(experiment, variant, metric, value, *others, paper=None):
    rows = [row(experiment, variant, metric, value, paper=paper)] + [row(experiment, *o) for o in others]
    return claims.judge(rows)[0]


@pytest.mark.parametrize("experiment,variant,metric,passing,failing", [
    ("b1_arx_bias", "forward", "loglog_slope", -0.45, -0.65),                 # within 0.1 of -0.5
    ("b1_arx_bias", "N100000", "inverse_to_forward_error", 10.0, 9.99),       # >= 10
    ("b1_linear_motor", "equation/newton/v0.05", "mae_over_direct", 0.8, 0.81),
    ("b1_linear_motor", "equation/analytic/v0.15", "peak_over_direct", 1 / 3, 0.34),  # <= paper (1/3)
    ("b1_linear_motor", "equation/direct/v0.2", "mae_over_physics", 0.99, 1.0),        # < 1 (strict)
    ("k_two_mass", "pgnn_none", "sk_stopped_on_tol", 1.0, 0.0),                         # is true
    ("k_two_mass", "rational", "sk_inner_solves_capped", 0.0, 1.0),
    ("b2_rot_trans", "n1=24/gamma=5e-05", "inversion_over_identification", 1.01, 1.0),  # > 1 (strict)
    ("b2_rot_trans", "trial=3/noise=False", "pgnn_rms_minus_linear_rms", 0.0, 1e-300),
    ("emps", "physics", "baseline/M", 95.1089 * 1.0199, 95.1089 * 1.0201),             # within 2% of paper
])
def test_each_test_form_decides_on_both_sides_of_its_threshold(experiment, variant, metric, passing, failing):
    ok = _judge(experiment, variant, metric, passing)
    bad = _judge(experiment, variant, metric, failing)
    assert ok["claim"] == bad["claim"] != "" and ok["claim_holds"] is True and bad["claim_holds"] is False
    assert _judge(experiment, variant, metric, math.nan)["claim_holds"] is False   # missing is not a pass


def test_row_references_compare_with_another_row_and_report_it_as_paper_value():
    below = _judge("k_two_mass", "pgnn_orthogonal/d0.03_v0.05", "sq_norm2", 1.0,
                   ("rational/d0.03_v0.05", "sq_norm2", 2.0), paper=0.0104)
    above = _judge("k_two_mass", "pgnn_orthogonal/d0.03_v0.05", "sq_norm2", 3.0,
                   ("rational/d0.03_v0.05", "sq_norm2", 2.0), ("rational/other", "sq_norm2", 9.0))
    assert below["claim_holds"] is True and above["claim_holds"] is False
    assert below["paper_value"] == 0.0104          # paper None in the table: the section's value stays
    x = _judge("emps", "pgnn-sim_error/test/data", "force_rel_error<physics", 3.0,
               ("physics/test/data", "force_rel_error", 3.5))
    assert x["claim"] == "X1" and x["claim_holds"] is True and x["paper_value"] == 3.5


def test_rows_no_condition_names_keep_no_verdict():
    for variant, metric in (("output/newton/v0.05", "mae_over_direct"),          # B1b is the equation noise
                            ("pgnn_orthogonal", "sk_stopped_on_tol"),             # K3: not the regularised PGNN
                            ("pgnn_orthogonal_lam0.1", "oe_check_improvement"),   # the λ sweep is no claim
                            ("regularizer=none/equation/newton/v0.05", "mae_over_direct")):
        r = _judge("b1_linear_motor" if "/" in variant and "pgnn" not in variant else "k_two_mass",
                   variant, metric, 0.0)
        assert r["claim"] == "" and r["claim_holds"] is None, (variant, metric)


def test_judge_is_idempotent():
    rows = [row("b2_rot_trans", "n1=32/gamma=1e-06", "abs_epsilon_over_tracking", 0.3)]
    once = [dict(r) for r in claims.judge(rows)]
    assert claims.judge(rows) == once and once[0]["claim_holds"] is False


def test_every_spec_claim_has_conditions_and_every_condition_reads():
    spec = (ROOT.parent / "shared" / "SPEC.md")
    ids = {c.claim for c in claims.CONDITIONS}
    if spec.exists():
        in_spec = set(re.findall(r"(?m)^\| (B1[a-c]|B2[a-e]|K[1-3]|X1) \|", spec.read_text()))
        assert in_spec and in_spec <= ids, sorted(in_spec - ids)
    for c in claims.CONDITIONS:
        t = c.test.split()
        assert t == ["is", "true"] or t[0] == "within" or t[0] in ("<", "<=", ">", ">="), c
        if t != ["is", "true"] and ":" not in c.test and not (c.paper is None and "paper" in c.test):
            assert math.isfinite(claims.threshold(c.claim, c.metric)) if _unique(c) else True
        c.text.format(**{k: "x" for k in re.findall(r"\{(\w+)", c.variant)})   # every text field is a variant field


def _unique(c) -> bool:
    return sum(d.claim == c.claim and d.metric == c.metric for d in claims.CONDITIONS) == 1


def test_sections_give_no_verdicts_of_their_own():
    """A verdict comes from the table only: the row helper takes no claim, and no section compares a
    quantity with a literal threshold to set ``claim_holds``."""
    with pytest.raises(TypeError):
        row("e", "v", "m", 1.0, "B1a", True)      # the old signature gave a verdict
    for f in (ROOT / "stages" / "report").glob("claims_*.py"):
        text = f.read_text()
        assert not re.search(r'claim_holds"?\]?\s*=\s*(?!None)', text), f.name   # clearing one is fine


def test_claim_table_names_the_fits_that_stopped_on_a_cap():
    """The header's claim table counts the experiment's runs stopped on a cap and names the fits behind
    them (issue 19: a non-zero cap cell names the fit and points at its tightening check)."""
    import pandas as pd

    from stages.report import _claim_table
    rows = [row("b2_rot_trans", "training", "fits_with_stop_reason", 32),
            row("b2_rot_trans", "training", "fits_stopped_on_cap", 2),
            row("b2_rot_trans", "n1=24", "fit_stopped_on_cap", 1.0),
            row("b2_rot_trans", "n1=32", "fit_stopped_on_cap", 0.0),
            row("b2_rot_trans", "n1=24/gamma=5e-05", "inversion_over_identification", 1.5),
            row("k_two_mass", "training", "fits_with_stop_reason", 4),
            row("k_two_mass", "training", "fits_stopped_on_cap", 0),
            row("k_two_mass", "pgnn_none", "sk_stopped_on_tol", 1.0)]
    table = pd.DataFrame(claims.judge(rows))
    table["claim"] = table["claim"].fillna("")
    lines = {ln.split("|")[1].strip(): ln for ln in _claim_table(table)[2:] if ln}
    b2 = next(v for k, v in lines.items() if k.startswith("B2"))
    assert "**2 of 32** (fit `n1=24`: no current tightening check" in b2 and "n1=32" not in b2
    # with a current tightening check of that fit, the row shows where its raised caps took it
    from types import SimpleNamespace
    t = SimpleNamespace(cost_ref=1.672e-9, cost_pert=6.463e-10, still_capped=True, max_value_change=0.9739)
    tight = {ln.split("|")[1].strip(): ln for ln in _claim_table(table, {("b2_rot_trans", "n1=24"): t})[2:] if ln}
    b2t = next(v for k, v in tight.items() if k.startswith("B2"))
    assert "training cost 1.67e-09 → 6.46e-10, on its cap again, its values move by up to 97%" in b2t
    k = next(v for k, v in lines.items() if k.startswith("K"))
    assert k.rstrip().endswith("| 0 of 4 |")


def test_claim_table_gives_each_verdict_in_the_checks_and_names_the_rows_that_flip_it():
    """A check that flips a claim's verdict (issue 19: B2c, tightened) shows it beside the claim, with the
    flipped row's two values and its fit's category; an unflipped claim reads "same", a claim whose
    experiment no check covers "not checked", and a claim of timings only is not compared."""
    import pandas as pd

    from pipeline.perturbation import claim_verdicts, compare
    from stages.report import _claim_table

    def summary(cost, rms, holds):
        return pd.DataFrame([
            ("b2", "", "n1=32", "fit_cost", cost, ""), ("b2", "", "n1=32", "fit_stopped_on_cap", 0.0, ""),
            ("b2", "B2c", "n1=32/noise=True/trial=6", "rms_over_ideal_rms", rms, holds),
            ("b2", "B2c", "n1=32/noise=False/trial=6", "rms_over_floor", 1.1, "true"),
            ("b2", "B2b", "n1=48", "id_over_n1", 0.3, "true"),
            ("b2", "B2d", "n1=32", "fhofc_seconds", 0.1, "true"),
            ("k", "K1", "pgnn", "ratio", 2.0, "true")],
            columns=["experiment", "claim", "variant", "metric", "value", "claim_holds"])
    ref = summary(6.48e-10, 1.78, "false")
    keys, _ = compare(ref[ref["experiment"] == "b2"], summary(6.73e-10, 1.44, "true"), rtol=0.01)
    v = claim_verdicts(keys).set_index("claim")
    assert not v.loc["B2c", "holds_ref"] and v.loc["B2c", "holds_pert"] and len(v.loc["B2c", "rows_changed"]) == 1
    assert v.loc["B2b", "holds_ref"] == v.loc["B2b", "holds_pert"] and v.loc["B2b", "rows_changed"] == []
    verdicts = {"tighten": {(r.experiment, r.claim): r for r in claim_verdicts(keys).itertuples()}}
    lines = {ln.split("|")[1].strip(): ln.split("|")[4].strip() for ln in _claim_table(ref, None, verdicts)[2:] if ln}
    assert lines["B2c"] == ("second machine: not checked; **tightened: yes** (`n1=32/noise=True/trial=6` "
                            "rms_over_ideal_rms 1.78 → 1.44, fit `n1=32` other minimum)")
    assert lines["B2b"] == "second machine: not checked; tightened: same"
    assert lines["K1"] == "second machine: not checked; tightened: not checked"
    assert lines["B2d"] == "a timing: the checks do not compare it"
