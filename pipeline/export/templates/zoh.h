/* Zero-order hold for a loop at ${NAME}_ZOH_N x the law's rate (Ts_loop = ${ts_loop} s): call
 * ${name}_zoh_step every loop sample with the reference at the loop rate,
 * r_fast[0 .. ${NAME}_ZOH_N * ${NAME}_PREVIEW] = r(t), ..., r(t + N P); every N-th call runs the law on
 * r_fast[0], r_fast[N], ..., r_fast[N P] and the output is held for N loop samples. */
#define ${NAME}_ZOH_N ${zoh_n}
#define ${NAME}_ZOH_PREVIEW (${NAME}_ZOH_N * ${NAME}_PREVIEW)
typedef struct {
    ${name}_state law;
    double u;
    uint64_t phase;      /* loop samples since the last law step */
} ${name}_zoh_state;
void ${name}_zoh_init(${name}_zoh_state *z, double r0);
double ${name}_zoh_step(${name}_zoh_state *z, const double *r_fast);
