void ${name}_zoh_init(${name}_zoh_state *z, double r0)
{
    ${name}_init(&z->law, r0);
    z->u = z->law.u_prev;       /* the guard's output before t = 0 */
    z->u_out = z->u;
    z->phase = 0;
    z->status = 0;
}

double ${name}_zoh_step(${name}_zoh_state *z, const double *r_fast)
{   /* zero-order hold: the law runs on every ${NAME}_ZOH_N-th loop sample; the slew limit per loop sample
     * (the law's is per law sample: rate * Ts in one loop sample would be N x the rate) */
    if (z->phase == 0u) {
        double rp[${NAME}_PREVIEW + 1];
        int i;
        for (i = 0; i <= ${NAME}_PREVIEW; ++i) rp[i] = r_fast[i * ${NAME}_ZOH_N];
        z->u = ${name}_step(&z->law, rp);
    }
    z->phase = (z->phase + 1u) % ${NAME}_ZOH_N;
    z->status = z->law.status;
    if (z->u - z->u_out > ${NAME}_ZOH_DU) { z->u_out = z->u_out + ${NAME}_ZOH_DU; z->status |= ${NAME}_RATE_LIMITED; }
    else if (z->u_out - z->u > ${NAME}_ZOH_DU) { z->u_out = z->u_out - ${NAME}_ZOH_DU; z->status |= ${NAME}_RATE_LIMITED; }
    else z->u_out = z->u;
    return z->u_out;
}
