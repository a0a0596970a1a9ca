#if AVERAGED   /* u(t) = (w(t) + w(t+1))/2 (SPEC §2.2): the law runs one sample ahead */
    if (!s->primed) { s->w_prev = law_w(s, r_preview + ADVANCE); s->primed = 1; }
    {
        const double w_next = law_w(s, r_preview + ADVANCE + 1);
#if defined(LAG_A0)   /* the actuator lag's inverse (pipeline.systems.actuator_lag): ZPETC preview, then its IIR */
        const double p = LAG_P0 * s->w_prev + LAG_P1 * w_next;
        u = (p + LAG_B1 * s->x[XLAG] - LAG_A1 * s->x[XLAG + 1]) / LAG_A0;
        s->x[XLAG] = p;
        s->x[XLAG + 1] = u;
#else
        u = 0.5 * (s->w_prev + w_next);
#endif
        s->w_prev = w_next;
    }
#else
    u = law_w(s, r_preview + ADVANCE);
#endif
