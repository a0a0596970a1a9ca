"""make install's uv step (scripts/uv_install.py): pip's configuration reaches uv as pip resolves it."""
from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
_spec = importlib.util.spec_from_file_location("uv_install", ROOT / "scripts" / "uv_install.py")
uv_install = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(uv_install)


def _pairs(cmd: list[str], flag: str) -> list[str]:
    return [cmd[i + 1] for i, a in enumerate(cmd[:-1]) if a == flag]


def test_real_pip_config_list_is_read_with_pip_precedence(tmp_path):
    """The installed pip's own `pip config list` output, from a config file with both sections: install over
    global, PIP_* over both, several values split on whitespace (multi-line values included)."""
    conf = tmp_path / "pip.conf"
    conf.write_text("[global]\nindex-url = https://mirror.example/simple\n"
                    "extra-index-url =\n    https://a.example/simple\n    https://b.example/simple\n"
                    "find-links = /global/wheels\ncert = /etc/team-ca.pem\n"
                    "[install]\nfind-links = /install/wheels\n")
    env = {k: v for k, v in os.environ.items() if not k.startswith("PIP_")}
    env.update(PIP_CONFIG_FILE=str(conf), PIP_TRUSTED_HOST="mirror.example")
    listed = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True, env=env,
                            check=True).stdout
    s = uv_install.pip_settings(listed, env)
    assert s["index-url"] == "https://mirror.example/simple"
    assert s["extra-index-url"].split() == ["https://a.example/simple", "https://b.example/simple"]
    assert s["find-links"] == "/install/wheels"          # [install] over [global], as pip
    assert s["trusted-host"] == "mirror.example"         # from PIP_TRUSTED_HOST
    assert s["cert"] == "/etc/team-ca.pem"
    cmd, uv_env, _ = uv_install.uv_command(["-e", ".[dev]"], s, "/venv/bin/python")
    assert _pairs(cmd, "--default-index") == ["https://mirror.example/simple"]
    assert _pairs(cmd, "--extra-index-url") == ["https://a.example/simple", "https://b.example/simple"]
    assert _pairs(cmd, "--index-strategy") == ["unsafe-best-match"]     # pip merges its indexes
    assert _pairs(cmd, "--find-links") == ["/install/wheels"]
    assert _pairs(cmd, "--allow-insecure-host") == ["mirror.example"]
    assert "--compile-bytecode" in cmd and cmd[-2:] == ["-e", ".[dev]"]
    assert uv_env == {"SSL_CERT_FILE": "/etc/team-ca.pem"}


def test_env_variable_replaces_the_config_value():
    listed = "global.find-links='/from/config'\nglobal.proxy='http://config-proxy:3128'\n"
    s = uv_install.pip_settings(listed, {"PIP_FIND_LINKS": "/from/env"})
    assert s["find-links"] == "/from/env"
    _, env, _ = uv_install.uv_command([], s, "python")
    assert env == {"HTTPS_PROXY": "http://config-proxy:3128", "HTTP_PROXY": "http://config-proxy:3128"}


def test_own_index_keeps_find_links_and_constraints_but_not_pips_indexes():
    """torch from PyTorch's CPU index: pip's indexes would compete with it; its find-links (a local CPU
    wheel) and its constraints still apply."""
    s = {"index-url": "https://mirror.example/simple", "extra-index-url": "https://a.example/simple",
         "find-links": "/opt/wheels", "constraint": "/etc/pip-constraints.txt"}
    cmd, _, _ = uv_install.uv_command(["torch==2.13.0", "--index-url", "https://download.pytorch.org/whl/cpu"], s, "py")
    assert "--default-index" not in cmd and "--extra-index-url" not in cmd and "--index-strategy" not in cmd
    assert _pairs(cmd, "--find-links") == ["/opt/wheels"]
    assert _pairs(cmd, "--constraint") == ["/etc/pip-constraints.txt"]
    assert _pairs(cmd, "--index-url") == ["https://download.pytorch.org/whl/cpu"]


def test_nothing_configured_adds_nothing():
    cmd, env, warnings = uv_install.uv_command(["uv"], uv_install.pip_settings("", {}), "py")
    assert cmd == ["py", "-m", "uv", "pip", "install", "--quiet", "--python", "py", "--compile-bytecode", "uv"]
    assert env == {} and warnings == []


def test_client_cert_timeout_retries_keyring_reach_uv_and_the_callers_uv_variables_win():
    """pip's client certificate, timeout (a float: whole seconds up for uv), retries and a keyring provider uv
    knows are handed over; make install's own UV_HTTP_TIMEOUT for PyTorch's index stays; a provider uv does
    not have is named, not passed."""
    listed = ("global.client-cert='/etc/me.pem'\nglobal.timeout='12.5'\nglobal.retries='7'\n"
              "install.keyring-provider='subprocess'\n")
    s = uv_install.pip_settings(listed, {})
    cmd, env, warnings = uv_install.uv_command(["x"], s, "py")
    assert env == {"SSL_CLIENT_CERT": "/etc/me.pem", "UV_HTTP_TIMEOUT": "13", "UV_HTTP_RETRIES": "7"}
    assert _pairs(cmd, "--keyring-provider") == ["subprocess"] and warnings == []
    _, env, _ = uv_install.uv_command(["x"], s, "py", {"UV_HTTP_TIMEOUT": "30"})
    assert "UV_HTTP_TIMEOUT" not in env and env["UV_HTTP_RETRIES"] == "7"
    s = uv_install.pip_settings("global.keyring-provider='import'\nglobal.timeout='soon'\n", {})
    cmd, env, warnings = uv_install.uv_command(["x"], s, "py")
    assert "--keyring-provider" not in cmd and env == {}
    assert len(warnings) == 2 and "keyring-provider=import" in warnings[0] and "UV_INSTALL=false" in warnings[0]
    assert "timeout" in warnings[1]
