/* main_ff_newton.c: test harness of ff_newton. Reads a reference (CSV, one value per line, header
 * lines before the first number skipped; any other line that is not exactly one number is an error),
 * writes u_ff (header "u_ff", one value per line, %.17g) to stdout and the number
 * of flagged samples to stderr. With --time R: runs the whole reference R times and prints the
 * median wall time per sample to stderr ("ns_per_sample=...").
 *   cc -std=c99 -O2 -Wall -Wextra -Werror -o main_ff_newton main_ff_newton.c ff_newton.c -lm
 *   ./main_ff_newton r_v0_05.csv > u_ff_c.csv */
#define _POSIX_C_SOURCE 199309L
#include <errno.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include "ff_newton.h"

#define LINE_MAX_BYTES 4096

static double *read_column(const char *path, long *n)
{   /* one number per line; lines before the first number are a header; anything else is an error
     * (a `t,r` CSV, a line cut by the buffer, text amid the data): never a silently wrong sample */
    FILE *f = fopen(path, "r");
    char line[LINE_MAX_BYTES];
    long cap = 4096, lineno = 0;
    double *r, *grown;
    if (!f) { fprintf(stderr, "error: cannot open %s\n", path); return NULL; }
    r = malloc((size_t)cap * sizeof *r);
    *n = 0;
    while (r && fgets(line, sizeof line, f)) {
        char *end, *p;
        double v;
        ++lineno;
        if (!strchr(line, '\n') && !feof(f)) {
            fprintf(stderr, "error: %s line %ld is longer than %d bytes\n", path, lineno, LINE_MAX_BYTES - 2);
            free(r); fclose(f); return NULL;
        }
        for (p = line; *p == ' ' || *p == '\t'; ++p) {}
        if (*p == '\n' || *p == '\r' || *p == '\0') continue;            /* empty line */
        v = strtod(p, &end);
        if (end == p) {
            if (*n == 0) continue;                                       /* header */
            fprintf(stderr, "error: %s line %ld is not a number\n", path, lineno);
            free(r); fclose(f); return NULL;
        }
        for (p = end; *p == ' ' || *p == '\t' || *p == '\r' || *p == '\n'; ++p) {}
        if (*p != '\0') {
            fprintf(stderr, "error: %s line %ld holds more than one value: give the reference r as one "
                    "column (as r_<reference>.csv)\n", path, lineno);
            free(r); fclose(f); return NULL;
        }
        if (*n == cap) {
            cap *= 2;
            grown = realloc(r, (size_t)cap * sizeof *r);
            if (!grown) { free(r); r = NULL; break; }
            r = grown;
        }
        r[(*n)++] = v;
    }
    fclose(f);
    if (!r) fprintf(stderr, "error: out of memory reading %s\n", path);
    return r;
}

static double run(const double *r, long n, double *u)
{   /* the reference sample by sample, as a real-time loop feeds it; returns Σ u */
    ff_newton_state s;
    double rp[FF_NEWTON_PREVIEW + 1], sum = 0.0;
    long t;
    int i;
    ff_newton_init(&s, FF_NEWTON_REST_AT_ZERO ? 0.0 : r[0]);
    for (t = 0; t < n; ++t) {
        double v;
        for (i = 0; i <= FF_NEWTON_PREVIEW; ++i) rp[i] = r[t + i < n ? t + i : n - 1];
        v = ff_newton_step(&s, rp);
        if (u) u[t] = v;
        sum += v;
    }
    if (u) fprintf(stderr, "samples flagged: %llu of %ld\n", (unsigned long long)s.n_flagged, n);
    return sum;
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
    long R = 0;
    if (argc == 4 && strcmp(argv[2], "--time") == 0) {     /* 1 <= R <= 10^6, a whole number */
        char *end;
        errno = 0;
        R = strtol(argv[3], &end, 10);
        if (errno || *end != '\0' || end == argv[3] || R < 1 || R > 1000000L) {
            fprintf(stderr, "error: --time needs a whole number of repeats in [1, 1000000], got %s\n", argv[3]);
            return 2;
        }
    } else if (argc != 2) {
        fprintf(stderr, "usage: %s REFERENCE.csv [--time REPEATS]\n", argv[0]);
        return 2;
    }
    r = read_column(argv[1], &n);
    if (!r) return 1;
    if (n == 0) { fprintf(stderr, "error: no samples in %s\n", argv[1]); return 1; }
    u = malloc((size_t)n * sizeof *u);
    if (!u) return 1;
    run(r, n, u);
    printf("u_ff\n");
    for (t = 0; t < n; ++t) printf("%.17g\n", u[t]);
    if (R > 0) {
        long k;
        double *ns = malloc((size_t)R * sizeof *ns);
        volatile double sink = 0.0;
        if (!ns) { fprintf(stderr, "error: out of memory for %ld timings\n", R); return 1; }
        for (k = 0; k < R; ++k) {
            struct timespec a, b;
            clock_gettime(CLOCK_MONOTONIC, &a);
            sink += run(r, n, NULL);
            clock_gettime(CLOCK_MONOTONIC, &b);
            ns[k] = ((double)(b.tv_sec - a.tv_sec) * 1e9 + (double)(b.tv_nsec - a.tv_nsec)) / (double)n;
        }
        qsort(ns, (size_t)R, sizeof *ns, cmp);
        fprintf(stderr, "ns_per_sample=%.2f\n", ns[R / 2]);
        free(ns);
    }
    free(r);
    free(u);
    return 0;
}
