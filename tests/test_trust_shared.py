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
