void ${name}_zoh_init(${name}_zoh_state *z, double r0)
{
    ${name}_init(&z->law, r0);
    z->u = 0.0;
    z->phase = 0;
}

double ${name}_zoh_step(${name}_zoh_state *z, const double *r_fast)
{   /* zero-order hold: the law runs on every ${NAME}_ZOH_N-th loop sample */
    if (z->phase == 0u) {
        double rp[${NAME}_PREVIEW + 1];
        int i;
        for (i = 0; i <= ${NAME}_PREVIEW; ++i) rp[i] = r_fast[i * ${NAME}_ZOH_N];
        z->u = ${name}_step(&z->law, rp);
    }
    z->phase = (z->phase + 1u) % ${NAME}_ZOH_N;
    return z->u;
}
