"""`uv pip install` for `make install`, with pip's own configuration handed over.

uv is pip-compatible on the command line but reads neither pip's configuration files nor its ``PIP_*``
variables. This passes on what decides where packages come from and which versions are allowed
(index-url, extra-index-url, find-links, constraint, trusted-host) and how to reach them (cert, proxy),
as pip itself resolves them: ``pip config list`` (every configuration file merged, the ``install``
section over ``global``) under the ``PIP_*`` variables. pip merges all its indexes; uv by default takes
a package from the first index that has it, so with extra indexes pip's way is asked for
(``--index-strategy unsafe-best-match``). Bytecode is compiled for everything installed (uv compiles
only on request, and only the packages of that one command).

Where the arguments name an index themselves (``--index-url``: torch from PyTorch's CPU index), pip's
indexes are not added; its find-links still are (a machine's local CPU torch wheel).

Usage (the venv's Python): ``python scripts/uv_install.py UV_PIP_INSTALL_ARGS...``; exits with uv's code.
"""
from __future__ import annotations

import ast
import os
import subprocess
import sys

#: pip options handed to uv as command-line arguments: pip's name -> uv's flag (several values: whitespace-separated)
FLAGS = {"index-url": "--default-index", "extra-index-url": "--extra-index-url", "find-links": "--find-links",
         "constraint": "--constraint", "trusted-host": "--allow-insecure-host"}
#: pip options handed to uv through its environment
ENV = {"cert": ("SSL_CERT_FILE",), "proxy": ("HTTPS_PROXY", "HTTP_PROXY")}


def pip_settings(config_list: str, environ: dict[str, str]) -> dict[str, str]:
    """pip's value of each option of FLAGS and ENV: ``PIP_<NAME>`` over ``install.<name>`` over
    ``global.<name>`` (``config_list``: the output of ``pip config list``, lines ``section.key='value'``)."""
    found: dict[str, dict[str, str]] = {}
    for line in config_list.splitlines():
        key, sep, value = line.partition("=")
        section, dot, name = key.partition(".")
        if not (sep and dot) or section not in ("global", "install"):
            continue
        try:
            found.setdefault(name, {})[section] = str(ast.literal_eval(value))
        except (ValueError, SyntaxError):
            found.setdefault(name, {})[section] = value.strip("'\"")
    out = {}
    for name in (*FLAGS, *ENV):
        env = environ.get("PIP_" + name.upper().replace("-", "_"))
        cfg = found.get(name, {})
        value = env if env is not None else cfg.get("install", cfg.get("global"))
        if value and value.strip():
            out[name] = value.strip()
    return out


def uv_command(args: list[str], settings: dict[str, str], python: str) -> tuple[list[str], dict[str, str]]:
    """The ``uv pip install`` command line and the environment additions for ``args`` under pip's ``settings``."""
    own_index = any(a == "--index-url" or a.startswith("--index-url=") for a in args)
    cmd = [python, "-m", "uv", "pip", "install", "--quiet", "--python", python, "--compile-bytecode"]
    for name, flag in FLAGS.items():
        if own_index and name in ("index-url", "extra-index-url"):
            continue
        for value in settings.get(name, "").split():
            cmd += [flag, value]
    if not own_index and settings.get("extra-index-url"):
        cmd += ["--index-strategy", "unsafe-best-match"]
    env = {var: settings[name] for name, vars_ in ENV.items() if name in settings for var in vars_}
    return cmd + list(args), env


def main(argv: list[str]) -> int:
    listed = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True)
    cmd, env = uv_command(argv, pip_settings(listed.stdout, dict(os.environ)), sys.executable)
    return subprocess.call(cmd, env={**os.environ, **env})


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
