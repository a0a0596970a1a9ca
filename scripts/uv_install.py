"""`uv pip install` for `make install`, with pip's own configuration handed over.

uv is pip-compatible on the command line but reads neither pip's configuration files nor its ``PIP_*``
variables. This passes on what decides where packages come from and which versions are allowed
(index-url, extra-index-url, find-links, constraint, trusted-host) and how to reach them (cert, client-cert,
proxy, timeout, retries, keyring-provider where uv has pip's value), as pip itself resolves them:
``pip config list`` (every configuration file merged, the ``install`` section over ``global``) under the
``PIP_*`` variables. pip merges all its indexes; uv by default takes
a package from the first index that has it, so with extra indexes pip's way is asked for
(``--index-strategy unsafe-best-match``). Bytecode is compiled for everything installed (uv compiles
only on request, and only the packages of that one command).

Where the arguments name an index themselves (``--index-url``: torch from PyTorch's CPU index), pip's
indexes are not added; its find-links still are (a machine's local CPU torch wheel).

uv's own ``UV_*`` variables in the caller's environment (``make install`` sets ``UV_HTTP_TIMEOUT=30`` for
PyTorch's CPU index) stay over pip's timeout and retries. A pip setting uv has no equivalent for
(keyring-provider ``auto``/``import``) is named on stderr: ``make install UV_INSTALL=false`` installs with pip.

Usage (the venv's Python): ``python scripts/uv_install.py UV_PIP_INSTALL_ARGS...``; exits with uv's code.
"""
from __future__ import annotations

import ast
import math
import os
import subprocess
import sys

#: pip options handed to uv as command-line arguments: pip's name -> uv's flag (several values: whitespace-separated)
FLAGS = {"index-url": "--default-index", "extra-index-url": "--extra-index-url", "find-links": "--find-links",
         "constraint": "--constraint", "trusted-host": "--allow-insecure-host",
         "keyring-provider": "--keyring-provider"}
#: pip options handed to uv through its environment
ENV = {"cert": ("SSL_CERT_FILE",), "client-cert": ("SSL_CLIENT_CERT",), "proxy": ("HTTPS_PROXY", "HTTP_PROXY"),
       "timeout": ("UV_HTTP_TIMEOUT",), "retries": ("UV_HTTP_RETRIES",)}
#: keyring providers uv knows (pip also has auto and import, which load Python's keyring in-process)
UV_KEYRING = ("disabled", "subprocess")


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


def _env_value(name: str, value: str) -> str:
    """pip's value as uv reads it: timeout in whole seconds (pip takes a float), retries an integer."""
    if name == "timeout":
        return str(max(1, math.ceil(float(value))))
    if name == "retries":
        return str(int(value))
    return value


def uv_command(args: list[str], settings: dict[str, str], python: str,
               environ: dict[str, str] | None = None) -> tuple[list[str], dict[str, str], list[str]]:
    """The ``uv pip install`` command line, the environment additions and the warnings (pip settings uv cannot
    take) for ``args`` under pip's ``settings``; ``environ``'s own ``UV_*`` variables are kept over pip's."""
    environ = {} if environ is None else environ
    own_index = any(a == "--index-url" or a.startswith("--index-url=") for a in args)
    cmd = [python, "-m", "uv", "pip", "install", "--quiet", "--python", python, "--compile-bytecode"]
    warnings = []
    for name, flag in FLAGS.items():
        if own_index and name in ("index-url", "extra-index-url"):
            continue
        for value in settings.get(name, "").split():
            if name == "keyring-provider" and value not in UV_KEYRING:
                warnings.append(f"pip's keyring-provider={value} has no uv equivalent (uv: {', '.join(UV_KEYRING)}); "
                                "if the index needs it, install with pip: make install UV_INSTALL=false")
                continue
            cmd += [flag, value]
    if not own_index and settings.get("extra-index-url"):
        cmd += ["--index-strategy", "unsafe-best-match"]
    env = {}
    for name, vars_ in ENV.items():
        if name not in settings:
            continue
        try:
            value = _env_value(name, settings[name])
        except ValueError:
            warnings.append(f"pip's {name}={settings[name]!r} is not a number; not handed to uv")
            continue
        env.update({var: value for var in vars_ if not (var.startswith("UV_") and var in environ)})
    return cmd + list(args), env, warnings


def main(argv: list[str]) -> int:
    listed = subprocess.run([sys.executable, "-m", "pip", "config", "list"], capture_output=True, text=True)
    cmd, env, warnings = uv_command(argv, pip_settings(listed.stdout, dict(os.environ)), sys.executable,
                                    dict(os.environ))
    for w in warnings:
        print("uv_install:", w, file=sys.stderr)
    return subprocess.call(cmd, env={**os.environ, **env})


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
