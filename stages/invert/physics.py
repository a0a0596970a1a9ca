"""invert.kind=physics: the analytic inverse of the identified physics model (SPEC §6)."""


def feedforward(ctx, name, r):
    return ctx.system.physics.feedforward(ctx.inputs["baseline"]["theta"], r)
