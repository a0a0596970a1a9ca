"""pgnn-feedforward: data-driven feedforward control with physics-guided neural networks."""
import os

# One BLAS/OpenMP thread per job unless the caller chose otherwise: a multi-threaded GEMM sums in
# another order, so the same config would give different trained models depending on how the job
# was started (measured on EMPS: test force error 4.73 vs 4.64 %). Parallelism comes from running
# jobs side by side (Hydra launchers), not from threads inside one. Set before numpy/torch load.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
