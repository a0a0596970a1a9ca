#if AVERAGED   /* u(t) = (w(t) + w(t+1))/2 (SPEC §2.2): the law runs one sample ahead */
    if (!s->primed) { s->w_prev = law_w(s, r_preview); s->primed = 1; }
    {
        const double w_next = law_w(s, r_preview + 1);
        u = 0.5 * (s->w_prev + w_next);
        s->w_prev = w_next;
    }
#else
    u = law_w(s, r_preview);
#endif
