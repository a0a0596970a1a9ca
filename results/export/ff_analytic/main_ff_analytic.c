/* main_ff_analytic.c: test harness of ff_analytic. Reads a reference (CSV, one value per line, header
 * lines before the first number skipped; any other line that is not exactly one number is an error;
 * nan/inf are read as such and go to the guard), writes u_ff (header "u_ff", one value per line,
 * %.17g) to stdout and the number of flagged samples to stderr.
 *   --flags      writes "u_ff,flags" (flags: the status bits of each sample)
 *   --time R     also runs the whole reference R times and prints the median wall time per sample
 *                to stderr ("ns_per_sample=...")
 *   --check V    the test vectors V (vectors_*.csv: r,u_ff,flags per line): runs r, compares u_ff per
 *                sample, |u_c(t) - u(t)| <= ATOL + RTOL |u(t)| (ATOL = 1.3313714102767901e-08 N, RTOL = 1e-09;
 *                manifest.json "check"), and the flags under CHECK_MASK exactly (all of them in double); exit 0 if all agree, 1 otherwise (the
 *                first mismatch on stderr)
 *   cc -std=c99 -O2 -Wall -Wextra -Werror -Wconversion -Wdouble-promotion -o main_ff_analytic main_ff_analytic.c ff_analytic.c -lm
 *   ./main_ff_analytic r_v0_05.csv > u_ff_c.csv
 *   ./main_ff_analytic --check vectors_normal.csv && echo ok */
#define _POSIX_C_SOURCE 199309L
#include <errno.h>
#include <math.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "ff_analytic.h"

#define LINE_MAX_BYTES 4096
#define CHECK_TOL 1e-09    /* RTOL: relative to |u(t)| of the sample */
#define CHECK_ATOL 1.3313714102767901e-08   /* ATOL [N]: from the law's scale (package.py check_bound) */
#define CHECK_MASK 1023   /* the flags compared exactly (float: not the threshold flags, check_bound) */

static double *read_columns(const char *path, int ncol, long *n)
{   /* ncol numbers per line (comma separated); lines before the first number are a header; anything
     * else is an error (a `t,r` CSV, a line cut by the buffer, text amid the data): never a silently
     * wrong sample. Returns n rows of ncol values, row-major. */
    FILE *f = fopen(path, "r");
    char line[LINE_MAX_BYTES];
    long cap = 4096, lineno = 0;
    double *r, *grown;
    if (!f) { fprintf(stderr, "error: cannot open %s\n", path); return NULL; }
    r = malloc((size_t)cap * (size_t)ncol * sizeof *r);
    *n = 0;
    while (r && fgets(line, sizeof line, f)) {
        char *end, *p;
        double v[3];
        int c;
        ++lineno;
        if (!strchr(line, '\n') && !feof(f)) {
            fprintf(stderr, "error: %s line %ld is longer than %d bytes\n", path, lineno, LINE_MAX_BYTES - 2);
            free(r); fclose(f); return NULL;
        }
        for (p = line; *p == ' ' || *p == '\t'; ++p) {}
        if (*p == '\n' || *p == '\r' || *p == '\0') continue;            /* empty line */
        for (c = 0; c < ncol; ++c) {
            v[c] = strtod(p, &end);
            if (end == p) break;
            p = end;
            if (c < ncol - 1) {
                if (*p != ',') { end = p; c = -1; break; }
                ++p;
            }
        }
        if (c == 0 && *n == 0) continue;                                 /* header */
        if (c != ncol) {
            fprintf(stderr, "error: %s line %ld is not %s\n", path, lineno, ncol == 1 ? "a number" : "r,u_ff,flags");
            free(r); fclose(f); return NULL;
        }
        for (; *p == ' ' || *p == '\t' || *p == '\r' || *p == '\n'; ++p) {}
        if (*p != '\0') {
            fprintf(stderr, "error: %s line %ld holds more than %s: give the reference r as one "
                    "column (as r_<reference>.csv)\n", path, lineno, ncol == 1 ? "one value" : "three values");
            free(r); fclose(f); return NULL;
        }
        if (*n == cap) {
            cap *= 2;
            grown = realloc(r, (size_t)cap * (size_t)ncol * sizeof *r);
            if (!grown) { free(r); r = NULL; break; }
            r = grown;
        }
        for (c = 0; c < ncol; ++c) r[*n * ncol + c] = v[c];
        (*n)++;
    }
    fclose(f);
    if (!r) fprintf(stderr, "error: out of memory reading %s\n", path);
    return r;
}

static double run(const double *r, long n, long stride, double *u, int *flags)
{   /* the reference sample by sample, as a real-time loop feeds it; returns the sum of u */
    ff_analytic_cc8ffc1b_state s;
    ff_analytic_cc8ffc1b_real rp[FF_ANALYTIC_CC8FFC1B_PREVIEW + 1];
    double sum = 0.0;
    long t;
    int i;
    ff_analytic_cc8ffc1b_init(&s, (ff_analytic_cc8ffc1b_real)(FF_ANALYTIC_CC8FFC1B_REST_AT_ZERO ? 0.0 : r[0]));
    for (t = 0; t < n; ++t) {
        double v;
        for (i = 0; i <= FF_ANALYTIC_CC8FFC1B_PREVIEW; ++i) rp[i] = (ff_analytic_cc8ffc1b_real)r[(t + i < n ? t + i : n - 1) * stride];
        v = (double)ff_analytic_cc8ffc1b_step(&s, rp);
        if (u) u[t] = v;
        if (flags) flags[t] = s.status;
        sum += v;
    }
    if (u) fprintf(stderr, "samples flagged: %llu of %ld\n", (unsigned long long)s.n_flagged, n);
    return sum;
}

static int check(const char *path)
{   /* the test vectors: r, u_ff, flags per line */
    long n, t;
    double *v = read_columns(path, 3, &n), *u;
    int *flags, bad = 0;
    if (!v) return 1;
    if (n == 0) { fprintf(stderr, "error: no vectors in %s\n", path); free(v); return 1; }
    u = malloc((size_t)n * sizeof *u);
    flags = malloc((size_t)n * sizeof *flags);
    if (!u || !flags) { free(v); free(u); free(flags); return 1; }
    run(v, n, 3, u, flags);
    for (t = 0; t < n && !bad; ++t) {   /* per sample: a spike elsewhere does not widen the bound here */
        const double want = v[3 * t + 1];
        if (!(fabs(u[t] - want) <= CHECK_ATOL + CHECK_TOL * fabs(want)) || (flags[t] & CHECK_MASK) != ((int)v[3 * t + 2] & CHECK_MASK)) {
            fprintf(stderr, "%s: sample %ld: u_ff %.17g flags %d, expected %.17g flags %d (|du| <= %g + %g |u|)\n",
                    path, t, u[t], flags[t], want, (int)v[3 * t + 2], CHECK_ATOL, CHECK_TOL);
            bad = 1;
        }
    }
    if (!bad) fprintf(stderr, "%s: %ld samples agree (|du| <= %g + %g |u| per sample, flags under mask %d exactly)\n",
                      path, n, CHECK_ATOL, CHECK_TOL, CHECK_MASK);
    free(v); free(u); free(flags);
    return bad;
}

static int cmp(const void *a, const void *b)
{
    const double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

int main(int argc, char **argv)
{
    long n, t;
    double *r, *u;
    int *flags = NULL, with_flags = 0;
    long R = 0;
    if (argc == 3 && strcmp(argv[1], "--check") == 0) return check(argv[2]);
    if (argc == 4 && strcmp(argv[2], "--time") == 0) {     /* 1 <= R <= 10^6, a whole number */
        char *end;
        errno = 0;
        R = strtol(argv[3], &end, 10);
        if (errno || *end != '\0' || end == argv[3] || R < 1 || R > 1000000L) {
            fprintf(stderr, "error: --time needs a whole number of repeats in [1, 1000000], got %s\n", argv[3]);
            return 2;
        }
    } else if (argc == 3 && strcmp(argv[2], "--flags") == 0) {
        with_flags = 1;
    } else if (argc != 2) {
        fprintf(stderr, "usage: %s REFERENCE.csv [--time REPEATS | --flags] | %s --check VECTORS.csv\n",
                argv[0], argv[0]);
        return 2;
    }
    r = read_columns(argv[1], 1, &n);
    if (!r) return 1;
    if (n == 0) { fprintf(stderr, "error: no samples in %s\n", argv[1]); free(r); return 1; }
    u = malloc((size_t)n * sizeof *u);
    if (with_flags) flags = malloc((size_t)n * sizeof *flags);
    if (!u || (with_flags && !flags)) { free(r); free(u); free(flags); return 1; }
    run(r, n, 1, u, flags);
    printf(with_flags ? "u_ff,flags\n" : "u_ff\n");
    for (t = 0; t < n; ++t) {
        if (with_flags) printf("%.17g,%d\n", u[t], flags[t]);
        else printf("%.17g\n", u[t]);
    }
    if (R > 0) {
        long k;
        double *ns = malloc((size_t)R * sizeof *ns);
        volatile double sink = 0.0;
        if (!ns) { fprintf(stderr, "error: out of memory for %ld timings\n", R); free(r); free(u); return 1; }
        for (k = 0; k < R; ++k) {
            struct timespec a, b;
            clock_gettime(CLOCK_MONOTONIC, &a);
            sink += run(r, n, 1, NULL, NULL);
            clock_gettime(CLOCK_MONOTONIC, &b);
            ns[k] = ((double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec)) / (double)n;
        }
        (void)sink;
        qsort(ns, (size_t)R, sizeof *ns, cmp);
        fprintf(stderr, "ns_per_sample=%.2f\n", ns[R / 2]);
        free(ns);
    }
    free(r);
    free(u);
    free(flags);
    return 0;
}
