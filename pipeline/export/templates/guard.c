/* ---- guard (issue 22): input sanitation, training envelope, fallback, saturation, slew limit ---- */
#define G_PREVIEW ${NAME}_PREVIEW
#define G_TS (${Ts})
#define U_LO (${sat_lo})           /* saturation [N] */
#define U_HI (${sat_hi})
#define DU_MAX (${du_max})         /* slew limit x Ts: the largest |u(t) - u(t-1)| [N] */
#define FALLBACK_KIND ${fallback_kind}        /* 0 hold, 1 physics, 2 ramp */
#define ENVELOPE_FALLS_BACK ${env_fallback}  /* 1: out of the envelope is invalid; 0: flagged only */
#define RAMP_N (${ramp_n})         /* ramp_time / Ts: samples of the ramp to 0 */
static const double ENV_LO[3] = {${env_lo}};   /* training envelope of r, dr/dt, d2r/dt2 */
static const double ENV_HI[3] = {${env_hi}};
#if FALLBACK_KIND == 1
static const double PHYS[3] = {${phys}};    /* physics fallback: M, F_v, F_c */
#endif

#define START_REST ${start_rest}        /* 1: init puts every state at rest at r0 (pipeline/invert/start.py) */
#define SETTLE_N ${settle_n}u          /* rest samples the law needs to reach its steady state */
#define STATIC_EXCLUDE ${static_exclude}  /* 1: the force at rest at r0 is taken off (the loop holds the load) */

void ${name}_init(${name}_state *s, double r0)
{
    const double r = isfinite(r0) ? r0 : 0.0;
    law_init(s, r);
#if START_REST   /* SETTLE_N + 1 law steps on a reference held at r0: the last is the law at rest, u_rest */
    {
        double rp[G_PREVIEW + 1], u = 0.0;
        uint64_t k;
        int i;
        for (i = 0; i <= G_PREVIEW; ++i) rp[i] = r;
        for (k = 0u; k <= SETTLE_N; ++k) u = law_step(s, rp);
        s->u_static = STATIC_EXCLUDE ? u : 0.0;
        s->u_prev = u - s->u_static;   /* the output before t = 0: the law at rest (no slew from 0 N) */
        s->u_hold = s->u_prev;
        s->status = 0;
        s->primed = 0;   /* an averaged input computes w(0) from the real preview at t = 0, as the study does */
    }
#endif
}

double ${name}_step(${name}_state *s, const double *r_preview)
{
    double ext[G_PREVIEW + 3];   /* r(t-2), r(t-1), r(t) .. r(t+P) after sanitation */
    double x[3], u;
    int i, j, flags = 0, invalid, inside = 1;
    ext[0] = s->r_hist[1];
    ext[1] = s->r_hist[0];
    for (i = 0; i <= G_PREVIEW; ++i) {
        if (isfinite(r_preview[i])) {
            ext[i + 2] = r_preview[i];
        } else {
            ext[i + 2] = ext[i + 1];
            flags |= ${NAME}_NONFINITE_INPUT;
        }
    }
    /* the envelope at every n = t .. t + P: the whole window r(t-2) .. r(t+P) the law is fed */
    for (j = 0; j <= G_PREVIEW; ++j) {
        x[0] = ext[j + 2];                                       /* r(n), n = t + j */
        x[1] = (ext[j + 2] - ext[j + 1]) / G_TS;                 /* backward differences */
        x[2] = (ext[j + 2] - 2.0 * ext[j + 1] + ext[j]) / (G_TS * G_TS);
        for (i = 0; i < 3; ++i) {
            if (!((ENV_LO[i] <= x[i]) && (x[i] <= ENV_HI[i]))) inside = 0;
        }
    }   /* x: the newest, n = t + P (the physics fallback's regressors) */
    if (!inside) flags |= ${NAME}_OUT_OF_RANGE;
    u = law_step(s, ext + 2);
#if START_REST
    u -= s->u_static;
#endif
    flags |= s->status;
    invalid = ((flags & ${NAME}_NONFINITE_INPUT) != 0) || !isfinite(u) || (ENVELOPE_FALLS_BACK && !inside);
    if (invalid) {
        flags |= ${NAME}_FALLBACK;
        if (s->n_invalid < UINT64_MAX) s->n_invalid++;
#if FALLBACK_KIND == 2                /* ramp to 0 over RAMP_N samples */
        {
            const double g = 1.0 - (double)s->n_invalid / RAMP_N;
            u = s->u_hold * (g > 0.0 ? g : 0.0);
        }
#elif FALLBACK_KIND == 1              /* physics on a finite reference, else hold */
        if ((flags & ${NAME}_NONFINITE_INPUT) == 0) {
            const double sg = x[1] > 0 ? 1.0 : (x[1] < 0 ? -1.0 : 0.0);
            u = PHYS[0] * x[2] + PHYS[1] * x[1] + PHYS[2] * sg;
            if (!isfinite(u)) u = s->u_hold;
        } else {
            u = s->u_hold;
        }
#else                                 /* hold */
        u = s->u_hold;
#endif
    } else {
        s->n_invalid = 0;
    }
    if (u > U_HI) { u = U_HI; flags |= ${NAME}_SATURATED; }
    else if (u < U_LO) { u = U_LO; flags |= ${NAME}_SATURATED; }
    if (u - s->u_prev > DU_MAX) { u = s->u_prev + DU_MAX; flags |= ${NAME}_RATE_LIMITED; }
    else if (s->u_prev - u > DU_MAX) { u = s->u_prev - DU_MAX; flags |= ${NAME}_RATE_LIMITED; }
    if (!invalid) s->u_hold = u;
    s->u_prev = u;
    s->r_hist[1] = s->r_hist[0];
    s->r_hist[0] = ext[2];
    s->status = flags;
    if (flags && s->n_flagged < UINT64_MAX) s->n_flagged++;
    if (s->k < UINT64_MAX) s->k++;
    return u;
}
