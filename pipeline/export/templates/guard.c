/* ---- guard (issue 22): input sanitation, training envelope, fallback, saturation, slew limit ---- */
#if defined(__FAST_MATH__) || (defined(__FINITE_MATH_ONLY__) && __FINITE_MATH_ONLY__)
/* -ffast-math (also implied by -Ofast) and -ffinite-math-only let the compiler assume no NaN/inf: it then
 * deletes every isfinite() below, and a NaN reference or an overflow reaches the actuator unflagged */
#error "${file}.c: do not build the guarded feedforward with -ffast-math, -Ofast or -ffinite-math-only: they delete every isfinite() check of the guard (a NaN reference or an overflow would reach the actuator with no flag); drop that flag (use -O2 or -O3)"
#endif
#define G_PREVIEW ${NAME}_PREVIEW
#define G_TS (${Ts})
#define U_LO (${sat_lo})           /* saturation [N] */
#define U_HI (${sat_hi})
#define DU_MAX (${du_max})         /* slew limit x Ts: the largest |u(t) - u(t-1)| [N] */
#define FALLBACK_KIND ${fallback_kind}        /* 0 hold, 1 physics, 2 ramp */
#define ENVELOPE_FALLS_BACK ${env_fallback}  /* 1: out of the envelope is invalid; 0: flagged only */
#define RAMP_N (${ramp_n})         /* ramp_time / Ts: samples of the ramp to 0 and of the return to the law */
static const double ENV_LO[3] = {${env_lo}};   /* training envelope of r, dr/dt, d2r/dt2 */
static const double ENV_HI[3] = {${env_hi}};
#if FALLBACK_KIND == 1   /* physics fallback M d2r + sum_j p_j T_j(r, dr), every force term of the system */
#define NPHYS ${n_phys}
static const double PHYS[NPHYS + 1] = {${phys}};          /* M, p_1 .. p_n */
static const int PHYS_CODES[NPHYS + 1] = {${phys_codes}};      /* T_j: pipeline.systems.force_terms codes */
static const double PHYS_CONSTS[NPHYS + 1] = {${phys_consts}}; /* shape constant of each T_j (+ one unused) */

${force_term}#endif

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
        if (!isfinite(u)) u = 0.0;     /* an absurd r0 overflowed the law: nothing to take off (Python alike) */
        s->u_static = STATIC_EXCLUDE ? u : 0.0;
        s->u_prev = u - s->u_static;   /* the output before t = 0: the law at rest (no slew from 0 N), */
        if (s->u_prev > U_HI) s->u_prev = U_HI;         /* inside the force limits (no slew from outside) */
        else if (s->u_prev < U_LO) s->u_prev = U_LO;
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
    int i, j, flags = 0, invalid, inside = 1, overflow = 0;
    ext[0] = s->r_hist[1];
    ext[1] = s->r_hist[0];
    if (s->r_bad != 0u) {      /* r(t-1) or r(t-2) was replaced: a step in the law's differences */
        flags |= ${NAME}_NONFINITE_INPUT;
    }
    for (i = 0; i <= G_PREVIEW; ++i) {
        if (isfinite(r_preview[i])) {
            ext[i + 2] = r_preview[i];
        } else {
            ext[i + 2] = ext[i + 1];
            flags |= ${NAME}_NONFINITE_INPUT;
        }
    }
    s->r_bad = ((s->r_bad << 1u) | (isfinite(r_preview[0]) ? 0u : 1u)) & 3u;
    /* the envelope at every n = t .. t + P: the whole window r(t-2) .. r(t+P) the law is fed */
    for (j = 0; j <= G_PREVIEW; ++j) {
        x[0] = ext[j + 2];                                       /* r(n), n = t + j */
        x[1] = (ext[j + 2] - ext[j + 1]) / G_TS;                 /* backward differences */
        x[2] = (ext[j + 2] - 2.0 * ext[j + 1] + ext[j]) / (G_TS * G_TS);
        for (i = 0; i < 3; ++i) {   /* a non-finite regressor (an overflow) is outside any envelope */
            if (!isfinite(x[i])) { overflow = 1; }
            if (!(isfinite(x[i]) && (ENV_LO[i] <= x[i]) && (x[i] <= ENV_HI[i]))) inside = 0;
        }
    }   /* x: the newest, n = t + P (the physics fallback's regressors) */
    if (!inside) flags |= ${NAME}_OUT_OF_RANGE;
    u = law_step(s, ext + 2);
#if START_REST
    u -= s->u_static;
#endif
    flags |= s->status;
    if (!isfinite(u)) { s->latched = 1; }   /* the law's state may hold inf/NaN: not trusted until init */
    if (s->latched != 0) { flags |= ${NAME}_SINGULAR; }
    /* invalid: a replaced input, an overflow (inf regressor, non-finite output, the law's SINGULAR: Newton
     * returns 0 N or its last finite iterate when it overflows), out of the envelope when that falls back */
    invalid = ((flags & (${NAME}_NONFINITE_INPUT | ${NAME}_SINGULAR)) != 0) || (overflow != 0) || (s->latched != 0)
              || (ENVELOPE_FALLS_BACK && !inside);
    if (invalid) {
        flags |= ${NAME}_FALLBACK;
        s->n_back = 0u;
        if (s->n_invalid < UINT64_MAX) s->n_invalid++;
#if FALLBACK_KIND == 2                /* ramp to 0 over RAMP_N samples */
        {
            const double g = 1.0 - (double)s->n_invalid / RAMP_N;
            u = s->u_hold * (g > 0.0 ? g : 0.0);
        }
#elif FALLBACK_KIND == 1              /* physics on a finite reference, else hold */
        if ((flags & ${NAME}_NONFINITE_INPUT) == 0) {
            u = PHYS[0] * x[2];
            for (j = 0; j < NPHYS; ++j) {
                u += PHYS[1 + j] * force_term(PHYS_CODES[j], PHYS_CONSTS[j], x[0], x[1]);
            }
            if (!isfinite(u)) u = s->u_hold;
        } else {
            u = s->u_hold;
        }
#else                                 /* hold */
        u = s->u_hold;
#endif
    } else {   /* back from a fallback: linearly from its last output to the law's over RAMP_N samples */
        if (s->n_invalid > 0u) { s->u_from = s->u_prev; s->n_back = 1u; }
        else if (s->n_back > 0u) { s->n_back++; }
        else { /* not returning */ }
        s->n_invalid = 0u;
        if (s->n_back > 0u) {
            const double g = (double)s->n_back / RAMP_N;
            if (g < 1.0) { u = s->u_from + (u - s->u_from) * g; flags |= ${NAME}_FALLBACK; }
            else { s->n_back = 0u; }
        }
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
