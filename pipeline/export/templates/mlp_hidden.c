    for (j = 0; j < ${rows}; ++j) {
        double z = G_B${layer}[j];
        for (i = 0; i < ${cols}; ++i) z += G_W${layer}[j * ${cols} + i] * h[i];
        o[j] = ${act};
    }
    for (j = 0; j < ${rows}; ++j) h[j] = o[j];
