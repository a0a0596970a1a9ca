"""Dataset I/O (Parquet + sidecar), bad-input errors, tracking metrics and the LS baseline solver."""
import json

import numpy as np
import pandas as pd
import pytest

from pipeline import data
from pipeline.identify.least_squares import solve_scaled
from pipeline.metrics import tracking_metrics


def _frame(n=50, seed=0):
    rng = np.random.default_rng(seed)
    return pd.DataFrame({"t": np.arange(n) * 1e-3, "r": rng.standard_normal(n),
                         "u": rng.standard_normal(n), "y": rng.standard_normal(n)})


def test_roundtrip_is_exact_and_sidecar_holds_meta(tmp_path):
    ds = data.Dataset(_frame(), {"Ts": 1e-3, "system": "toy", "seed": 3})
    path = data.save(ds, tmp_path / "set")
    assert path.suffix == ".parquet" and path.with_suffix(".json").exists()
    back = data.load(path)
    pd.testing.assert_frame_equal(back.frame, ds.frame, check_exact=True)
    assert json.loads(path.with_suffix(".json").read_text())["seed"] == 3
    assert back.Ts == 1e-3
    assert not list(tmp_path.glob(".*tmp*"))  # atomic write leaves no temporary file


def test_nan_in_loaded_data_is_named(tmp_path):
    df = _frame()
    df.loc[17, "y"] = np.nan
    df.to_parquet(tmp_path / "bad.parquet")
    with pytest.raises(ValueError, match=r"column 'y' has 1 NaN/inf.*row 17"):
        data.load(tmp_path / "bad.parquet")


def test_missing_file_and_missing_column(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        data.load(tmp_path / "nope.parquet")
    with pytest.raises(ValueError, match=r"missing column\(s\) \['y'\]"):
        data.Dataset(_frame().drop(columns="y"), {"Ts": 1e-3})


def test_emps_loader_reads_real_data():
    from pathlib import Path
    folder = Path(__file__).resolve().parents[2] / "shared" / "data" / "emps"
    if not folder.exists():
        pytest.skip("../shared/data/emps not beside the repo")
    ds = data.load_emps(folder)
    assert len(ds) == 24841 and ds.Ts == pytest.approx(1e-3, rel=1e-4)  # t stored in float, 1 ms
    # force = gtau * vir with gtau = 35.150652 N/V (EMPS README)
    assert ds.meta["gtau"] == pytest.approx(35.150652, rel=1e-7)  # README gives 8 digits


def test_tracking_metrics_closed_form():
    r = np.array([0.0, 1.0, 2.0, 3.0])
    y = np.array([0.0, 0.5, 2.5, 1.0])      # e = [0, .5, -.5, 2]
    m = tracking_metrics(r, y, f_hat=np.array([3.0, 4.0]), f=np.array([0.0, 0.0]))
    assert m["mae"] == pytest.approx(0.75, rel=1e-15)
    assert m["max_abs"] == 2.0
    assert m["sq_norm2"] == pytest.approx(4.5, rel=1e-15)
    assert m["rms"] == pytest.approx(np.sqrt(4.5 / 4), rel=1e-15)
    assert m["ff_error"] == pytest.approx(5.0, rel=1e-15) and m["ff_error_rel"] == pytest.approx(1.0)
    with pytest.raises(ValueError, match="one shape"):
        tracking_metrics(r, y[:3])


def test_scaled_least_squares_matches_lstsq_and_flags_rank_deficiency():
    rng = np.random.default_rng(1)
    Phi = rng.standard_normal((200, 3)) * np.array([1e-6, 1.0, 1e6])  # badly scaled columns
    theta = np.array([2e5, -1.5, 3e-7])
    z = Phi @ theta
    np.testing.assert_allclose(solve_scaled(Phi, z), theta, rtol=1e-10)
    Phi[:, 2] = 2.0 * Phi[:, 1]
    with pytest.raises(ValueError, match="rank deficient"):
        solve_scaled(Phi, z)


def test_motion_phases_match_the_designed_segment_times():
    # out-and-back of two third-order moves (SPEC §1): the accelerating samples are the 4 t_j + 2 t_a
    # of each move, the constant-velocity ones its t_v, the rest standstill; central differences
    # may move each of the 8 phase boundaries by at most 2 samples
    from pipeline.metrics import motion_phases, phase_peaks
    from pipeline.references import move_times, out_and_back
    Ts = 1e-3
    r = out_and_back(0.1, 0.1, 4.0, 1000.0, Ts).r
    mt = move_times(0.1, 0.1, 4.0, 1000.0)
    m = motion_phases(r)
    designed = {"accel": 2 * (4 * mt.t_j + 2 * mt.t_a) / Ts, "constvel": 2 * mt.t_v / Ts}
    designed["standstill"] = r.size - designed["accel"] - designed["constvel"]
    for k, n in designed.items():
        assert abs(m[k].sum() - n) <= 2 * 8, (k, m[k].sum(), n)
    assert sum(m[k].astype(int) for k in m).max() == 1  # a partition
    # the peak per phase: a known error placed in the middle of one segment of each phase
    e = np.zeros_like(r)
    for k, val in (("accel", 2.0), ("constvel", 3.0), ("standstill", 1.0)):
        idx = np.flatnonzero(m[k])
        e[idx[len(idx) // 2]] = val
    assert phase_peaks(r, r - e) == {"max_abs_accel": 2.0, "max_abs_constvel": 3.0, "max_abs_standstill": 1.0}
    # force error per phase: 3 N wherever the reference accelerates, 0 elsewhere
    from pipeline.metrics import phase_ff_errors
    f_hat = np.sin(np.arange(r.size))
    err = phase_ff_errors(r, f_hat, f_hat + 3.0 * m["accel"])
    assert err == {"ff_rms_accel": 3.0, "ff_rms_constvel": 0.0, "ff_rms_standstill": 0.0}
    with pytest.raises(ValueError, match="at least 3 samples"):
        motion_phases(np.zeros(2))
