"""kpi_calib_ros: KPI-based laser-tracker calibration of industrial manipulators."""
import os

# Our matrices are small (at most a few thousand rows by ~60 columns). A multi-threaded
# BLAS only spins against other processes on the same cores (seen: 100x slower
# identification next to a busy core). Set before numpy loads; the user can override.
for _var in ('OPENBLAS_NUM_THREADS', 'OMP_NUM_THREADS', 'MKL_NUM_THREADS'):
    os.environ.setdefault(_var, '1')
