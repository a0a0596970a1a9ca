"""invert.kind=exact: the simulator's exact optimal input (only where the plant knows it)."""
from pipeline.runner import ConfigError
from pipeline.systems.base import System


def check(cfg, system) -> None:
    if type(system).exact_inverse is System.exact_inverse:
        raise ConfigError(f"invert.kind=exact: system '{system.name}' has no exact inverse; "
                          "use invert=physics or an identified model")


def feedforward(ctx, name, r):
    return ctx.system.exact_inverse(r)
