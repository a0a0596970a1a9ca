static inline double df2t(double *z, double x)
{   /* one sample of lfilter(NUM, DEN, x): y = z0 + b0 x, z_i = z_{i+1} + b_{i+1} x - a_{i+1} y */
    int i;
    const double y = z[0] + NUM[0] * x;
    for (i = 0; i < NDEN - 2; ++i) z[i] = z[i + 1] + x * NUM[i + 1] - y * DEN[i + 1];
    if (NDEN > 1) z[NDEN - 2] = x * NUM[NDEN - 1] - y * DEN[NDEN - 1];
    return y;
}
