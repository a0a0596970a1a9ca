static inline double force_term(int code, double p, double q, double v)
{   /* T(q, q̇) of one force term (pipeline.systems.force_terms.term, codes of ForceTerms; guard.py _term) */
    const double sg = v > 0 ? 1.0 : (v < 0 ? -1.0 : 0.0);
    double x, t;
    int k;
    switch (code) {
    case 0: return v;                             /* viscous */
    case 1: return sg;                            /* Coulomb, sign */
    case 2: return tanh(v / p);                   /* Coulomb, smooth */
    case 3: x = v / p; return sg * exp(-(x * x)); /* Stribeck */
    case 4: return 1.0;                           /* offset (gravity) */
    case 5: return cos(p * q);                    /* cogging cos */
    case 6: return sin(p * q);                    /* cogging sin */
    case 7: return v * fabs(v);                   /* drag */
    default:                                      /* (q/p)^k, k = code - 7: spring (k = 1, p = 1), position_poly */
        x = q / p;
        t = x;
        for (k = code - 7; k > 1; --k) t = t * x;
        return t;
    }
}
