/* Zero-order hold for a loop at ${NAME}_ZOH_N x the law's rate (Ts_loop = ${ts_loop} s, ${NAME}_ZOH_TS_NS ns:
 * ${NAME}_LOOP_TS_NS may be this period): call ${name}_zoh_step every loop sample with the reference at the
 * loop rate, r_fast[0 .. ${NAME}_ZOH_N * ${NAME}_PREVIEW] = r(t), ..., r(t + N P); every N-th call runs the
 * law on r_fast[0], r_fast[N], ..., r_fast[N P] and its output is held for N loop samples, reached by a ramp
 * at the slew limit per LOOP sample, |u(t) - u(t-1)| <= rate * Ts_loop = ${NAME}_ZOH_DU N (z->status: the
 * law's flags of its last step, plus RATE_LIMITED when this loop sample was ramped). */
#define ${NAME}_ZOH_N ${zoh_n}
#define ${NAME}_ZOH_TS_NS ${zoh_ts_ns}
#define ${NAME}_ZOH_DU (${du_loop})
#define ${NAME}_ZOH_PREVIEW (${NAME}_ZOH_N * ${NAME}_PREVIEW)
typedef struct {
    ${name}_state law;
    double u;            /* the law's last output (the target) */
    double u_out;        /* the wrapper's last output */
    uint64_t phase;      /* loop samples since the last law step */
    int status;          /* the law's flags of its last step | RATE_LIMITED of this loop sample */
} ${name}_zoh_state;
void ${name}_zoh_init(${name}_zoh_state *z, double r0);
double ${name}_zoh_step(${name}_zoh_state *z, const double *r_fast);
