static inline double force_term(int code, double p, double q, double v)
{   /* T(q, q̇) of one expanded column (pipeline.systems.force_terms.term, codes of ForceTerms) */
    const double sg = v > 0 ? 1.0 : (v < 0 ? -1.0 : 0.0);
    double x;
    switch (code) {
    case 0: return v;                            /* viscous */
    case 1: return sg;                           /* Coulomb, sign */
    case 2: return tanh(v / p);                  /* Coulomb, smooth */
    case 3: x = v / p; return sg * exp(-(x * x)); /* Stribeck */
    case 4: return 1.0;                          /* offset */
    case 5: return cos(p * q);                   /* cogging cos */
    default: return sin(p * q);                  /* cogging sin */
    }
}
