#if HAS_CTRL   /* minus the controller's force on y = r: gtau (C_r - C_y) r */
#if START_REST_CTRL
    u = u - GTAU * (df2t(s->x + XZ, r_preview[0] - s->x[XR0]) + K0 * s->x[XR0]);
#else
    u = u - GTAU * df2t(s->x + XZ, r_preview[0]);
#endif
#endif
