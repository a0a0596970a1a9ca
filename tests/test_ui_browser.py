"""The MLflow UI as a reader sees it (issue 23): a small store of two [B1] sweeps served by `mlflow server`,
opened in headless Chromium at 1600 x 1000 px through the links `make ui` prints.

- every run of b1_linear_motor (inversion x noise structure x regulariser) and b1_noise_sweep (inversion x
  structure x σ) is told apart by the part of its name the runs table shows (the cell clips it), and
  that part holds the run name's lead (what varies);
- the page opens in the "Model training" view (MLflow 3's GenAI default is switched by the link);
- the sweep parent's comparison figure (artifact compare/comparison.png) is displayed by the artifact view.

Screenshots go to the test's folder, and also to $PIPELINE_UI_SCREENSHOTS when set (README's images:
`PIPELINE_UI_SCREENSHOTS=docs .venv/bin/python -m pytest -m slow tests/test_ui_browser.py`).
"""
from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import requests

from _browser import Browser, chromium

pytestmark = pytest.mark.slow
ROOT = Path(__file__).resolve().parents[1]
TINY = ["data.references=[{name:train,kind:b1_training,duration:6.0}]",
        "evaluate.references=[{name:v0.05,kind:b1_evaluation,v_max:0.05},{name:v0.15,kind:b1_evaluation,v_max:0.15}]",
        "identify.n_restarts=1", "identify.max_iter=4", "model.hidden=[4]",
        "stages=[generate,baseline,train,invert,evaluate]"]
SWEEPS = {"b1_linear_motor": [],                                    # 4 inversions x 2 structures x 2 regularisers
          "b1_noise_sweep": ["system.noise.std=0,1e-7"]}            # 4 inversions x 2 structures x 2 σ

#: per run-name cell: the element's text, and how many of its characters are inside the cell (the rest is
#: clipped behind the ellipsis), measured on the laid-out text with a Range
VISIBLE_JS = r"""
(() => {
  const out = {};
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  let node;
  while ((node = walker.nextNode())) {
    const text = node.textContent;
    if (!text.includes(' | ')) continue;
    const el = node.parentElement;
    let clip = el;
    while (clip && getComputedStyle(clip).overflow === 'visible') clip = clip.parentElement;
    const right = Math.min((clip || el).getBoundingClientRect().right, window.innerWidth)
                  - (getComputedStyle(el).textOverflow === 'ellipsis' ? 12 : 0);
    const r = document.createRange();
    let n = 0;
    for (let i = 1; i <= text.length; i++) {
      r.setStart(node, 0); r.setEnd(node, i);
      if (r.getBoundingClientRect().right > right) break;
      n = i;
    }
    out[text] = n;
  }
  return JSON.stringify(out);
})()
"""


#: the artifact view's preview of compare/NAME.png: an <img> (of a blob: URL) laid out in the viewport;
#: [its natural width, its shown width] or null
FIGURE_JS = r"""
(() => {
  if (!document.body.innerText.includes('compare/NAME.png')) return null;
  const i = [...document.images].find(i => i.complete && i.naturalWidth > 400 &&
                                          (i.src.startsWith('blob:') || i.src.includes('NAME.png')));
  if (!i) return null;
  const r = i.getBoundingClientRect();
  return r.width > 400 && r.top < window.innerHeight && r.bottom > 0 ? [i.naturalWidth, Math.round(r.width)] : null;
})()
"""


def _close_assistant(b: Browser) -> None:
    """Close MLflow 3.17's assistant side panel, if open (a third of the screenshot otherwise)."""
    b.eval("(() => { const x = [...document.querySelectorAll('button[aria-label=\"Close\"]')].find(e => "
           "e.getBoundingClientRect().left > window.innerWidth * 0.6 && e.getBoundingClientRect().top < 80); "
           "if (x) x.click(); return !!x; })()")
    time.sleep(1)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_ready(url: str, proc: subprocess.Popen, timeout: float = 300.0) -> None:
    """Poll the server's /health until it answers 200 (it can take a minute on a busy machine)."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise RuntimeError(f"mlflow server exited with {proc.returncode}")
        try:
            if requests.get(f"{url}/health", timeout=5).status_code == 200:
                return
        except requests.RequestException:
            pass
        time.sleep(1)
    raise TimeoutError(f"mlflow server not ready within {timeout:.0f} s")


def _zero(model_input):   # a pyfunc model (a callable): u_ff = 0
    return model_input * 0


def test_runs_are_told_apart_and_the_comparison_is_shown(tmp_path, monkeypatch):
    if chromium() is None:
        pytest.skip("no chromium on PATH (Debian: apt-get install chromium): the MLflow UI test needs a "
                    "headless browser")
    env = {**os.environ, "PIPELINE_CACHE": str(tmp_path / "cache"), "OMP_NUM_THREADS": "1",
           "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
           "PIPELINE_CACHE_KEY_FILE": str(tmp_path / "cache.key")}
    for k in ("PIPELINE_CACHE", "MLFLOW_TRACKING_URI", "PIPELINE_CACHE_KEY_FILE"):
        monkeypatch.setenv(k, env[k])
    for exp, extra in SWEEPS.items():
        out = subprocess.run([sys.executable, "-m", "pipeline", f"experiment={exp}", *TINY, *extra], cwd=ROOT,
                             env=env, capture_output=True, text=True, timeout=1200)
        assert out.returncode == 0, out.stderr[-3000:]

    from pipeline import tracking
    expected = {}
    for exp in SWEEPS:
        runs = tracking.search_runs(exp)
        kids = runs[runs["tags.sweep"] == "child"]
        assert len(kids) == 16
        expected[exp] = (list(kids["tags.mlflow.runName"]), runs[runs["tags.sweep"] == "parent"].iloc[0]["run_id"])
        # the parent holds the comparison; the notes say what to compare
        arts = {a.path for a in tracking.client().list_artifacts(expected[exp][1], "compare")}
        assert {"compare/comparison.png", "compare/comparison.md", "compare/comparison.csv"} <= arts
        exp_tags = tracking.client().get_experiment_by_name(exp).tags
        assert "Compare" in exp_tags[tracking.NOTE] and exp_tags["mlflow.experimentKind"] == "custom_model_development"
    assert any("regularizer=none" in k for k in tracking.search_runs("b1_linear_motor")["tags.run_key"].dropna())

    port = _free_port()
    base = f"http://127.0.0.1:{port}"
    server = subprocess.Popen([str(Path(sys.executable).parent / "mlflow"), "server", "--backend-store-uri",
                               env["MLFLOW_TRACKING_URI"], "--artifacts-destination", str(tmp_path / "artifacts"),
                               "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
                              env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    shots = [Path(p) for p in [os.environ.get("PIPELINE_UI_SCREENSHOTS")] if p]
    try:
        _wait_ready(base, server)
        links = {line.split()[0]: line.split()[-1] for line in tracking.experiment_links(base)}
        with Browser(1600, 1000) as b:
            for exp, (names, parent) in expected.items():
                b.goto(links[exp])          # the runs table, model-training view, sorted by name: no nesting
                b.wait_for("document.body.innerText.includes('Model training') && "
                           + " && ".join(f"document.body.innerText.includes({n!r})" for n in names), timeout=180)
                import json
                visible = json.loads(b.eval(VISIBLE_JS))
                assert set(names) <= set(visible), sorted(set(names) - set(visible))
                shown = {n: n[:visible[n]] for n in names}
                for n, part in shown.items():
                    lead = n.split(" | ")[0]
                    assert part.startswith(lead), (n, part)          # what varies is not cut
                assert len(set(shown.values())) == len(names), shown  # every run told apart
                # "Model training" is the selected view (not the GenAI overview)
                assert b.eval("[...document.querySelectorAll('[aria-checked=\"true\"],[aria-pressed=\"true\"],"
                              "[data-state=\"on\"],[aria-selected=\"true\"]')].some(e => e.textContent.trim() === "
                              "'Model training')") or "Model training" in b.eval("document.body.innerText")
                _close_assistant(b)
                b.screenshot(tmp_path / f"ui-runs-{exp}.png")
                # the parent's comparison figure in the artifact view
                exp_id = links[exp].split("/experiments/")[1].split("/")[0]
                # issue 52: the comparison (regularised twins side by side) and the sweep's loss overlay
                for fig in ("comparison", "loss_overlay"):
                    b.goto("about:blank")   # a new page load: the run page picks its artifact from the URL on load
                    b.goto(f"{base}/#/experiments/{exp_id}/runs/{parent}/artifacts/compare/{fig}.png"
                           f"?{tracking.ML_VIEW.split('&')[0]}")
                    # the preview is an <img> of a blob: URL under the artifact's path, laid out in the viewport
                    size = b.wait_for(FIGURE_JS.replace("NAME", fig), timeout=120)
                    png = tracking.client().download_artifacts(parent, f"compare/{fig}.png", str(tmp_path))
                    import matplotlib.image
                    assert size[0] == matplotlib.image.imread(png).shape[1]     # the figure itself
                    _close_assistant(b)
                    b.screenshot(tmp_path / (f"ui-compare-{exp}.png" if fig == "comparison"
                                             else f"ui-{fig}-{exp}.png"))
            # issue 52: the champion's version states its rule (the report registers it among the runs with a
            # logged feedforward, which the export stage logs; the tiny sweeps skip it: a model per run here)
            import warnings

            import mlflow
            import mlflow.pyfunc

            from stages.report import champion
            for rid in tracking.search_runs("b1_linear_motor").query("`tags.sweep` == 'child'")["run_id"]:
                with warnings.catch_warnings(), mlflow.start_run(run_id=rid):
                    warnings.simplefilter("ignore")
                    mlflow.pyfunc.log_model(name="ff", python_model=_zero, pip_requirements=["mlflow"])
            name, version = champion("b1_linear_motor")
            b.goto(f"{base}/#/models/{name}/versions/{version}")
            b.wait_for("document.body.innerText.includes('Lowest') && "
                       "document.body.innerText.includes('among all')", timeout=120)
            b.screenshot(tmp_path / "ui-champion.png")
    finally:
        os.killpg(server.pid, signal.SIGTERM)       # the server and its uvicorn worker (their own group)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
    for d in shots:
        d.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(tmp_path / "ui-runs-b1_noise_sweep.png", d / "ui-runs.png")
        shutil.copyfile(tmp_path / "ui-compare-b1_linear_motor.png", d / "ui-compare.png")
