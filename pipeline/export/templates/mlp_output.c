    { double z = ${start};
      for (i = 0; i < ${cols}; ++i) z += G_W${layer}[i] * h[i];
      (void)o; (void)j;
      return G_GAIN * z; }
}
