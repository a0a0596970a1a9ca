"""Which [K] PGNN's restarts are screened (stages/train/sk_oe.py, ``identify.screen_restarts_of``; issue 19).

K2's spread of f_M is taken over the restarts, so with the regulariser every restart runs to its own SK stop
(a spread of converged fits); without it (θ not unique, restarts crawl along that valley) they stay screened.
The k_two_mass data, a 2-neuron MLP and two restarts on small SK/LM budgets: what is checked is which restarts
ran past the screening budget, read from each restart's logged stop detail (its SK iteration count).
"""
import re

import pytest

SMALL = ["experiment=k_two_mass", "model=pgnn_shared_ar", "stages=[generate,baseline,train]", "hydra.mode=RUN",
         "model.hidden=[2]", "identify.n_restarts=2", "identify.n_jobs=1", "identify.max_iter=3",
         "identify.lm_max_iter=3", "identify.oe_check_iter=3", "identify.screen_max_iter=1",
         "identify.screen_lm_max_iter=2", "identify.tol=1e-300", "identify.cost_tol=0", "identify.stall_window=0"]


def _restart_sk_iterations(run_name):
    from pipeline import tracking
    runs = tracking.search_runs("k_two_mass").set_index("tags.mlflow.runName")
    r = runs.loc[run_name]
    return r, [int(re.search(r"after (\d+) SK iteration", r[f"tags.stop_detail.restart{i}"]).group(1))
               for i in range(2)]


@pytest.mark.parametrize("reg, which, screened", [("orthogonal", "unregularized", False),
                                                   ("none", "unregularized", True),
                                                   ("orthogonal", "all", True)])
def test_only_the_unregularised_pgnn_screens_its_restarts_by_default(store, cfg_of, reg, which, screened):
    from pipeline import runner
    name = f"{reg}-{which}"
    runner.run_job(cfg_of(*SMALL, f"regularizer={reg}", f"identify.screen_restarts_of={which}", f"run_name={name}"))
    run, its = _restart_sk_iterations(name)
    if screened:   # the kept restart runs on to the cap (3), the other keeps the screening budget (1)
        assert sorted(its) == [1, 3] and run["metrics.train/screened_restarts"] == 2
    else:          # every restart runs to its own stop: here the SK cap, 3 iterations each
        assert its == [3, 3] and "metrics.train/screened_restarts" not in run.index


def test_k2_flag_names_each_models_own_budget_and_only_the_capped_ones():
    """The report's K2 flag: the unregularised PGNN's screened restarts count as stopped on the screening budget,
    the regularised PGNN's (each run to its SK stop) on the SK cap; a model whose restarts all stopped on their
    tolerances is not flagged."""
    from stages.report.claims_k import _k2_caps
    none = {"train/sk_not_converged_restarts": 4.0, "train/sk_inner_capped_restarts": 4.0,
            "train/screened_restarts": 5.0}
    orth = {"train/sk_not_converged_restarts": 0.0, "train/sk_inner_capped_restarts": 0.0}
    txt = _k2_caps(none, orth)
    assert txt.startswith("- **Flag: K2 is fed by fits that stopped on a cap** (none: 4 of the restarts stopped on "
                          "the screening budget")
    assert "orthogonal: 0" not in txt and "every orthogonal restart stopped on its tolerances" in txt
    orth_capped = {**orth, "train/sk_not_converged_restarts": 1.0}
    assert "orthogonal: 1 of the restarts stopped on the SK cap" in _k2_caps(none, orth_capped)
    clean = {"train/sk_not_converged_restarts": 0.0, "train/sk_inner_capped_restarts": 0.0}
    assert _k2_caps(clean, clean).startswith("- every restart feeding K2 stopped on its tolerances")
