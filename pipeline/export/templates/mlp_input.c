static inline double approximator(const double *win)
{   /* g_φ(window) = G_GAIN · MLP((window - mean)/std), [K] (4) */
    double h[${buf}], o[${buf}];
    int i, j;
    for (i = 0; i < ${n_in}; ++i) h[i] = (win[i] - W_MEAN[i]) / W_STD[i];
