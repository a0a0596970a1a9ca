"""invert.kind=physics: the analytic inverse of the identified physics model (SPEC §6)."""

VERSION = 2   # 2: averaged model input: w(N) is the law's next sample on the held reference (pipeline.export)


def feedforward(ctx, name, r):
    return ctx.system.physics.feedforward(ctx.inputs["baseline"]["theta"], r)
