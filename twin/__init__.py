"""The MuJoCo digital twin: real machines built from a nominal MJCF model plus errors and effects,
placed at commanded motor angles, simulated, and measured with a virtual laser tracker."""

import os

# Rendering is offscreen only: pick EGL unless the user chose a backend, before MuJoCo is imported.
os.environ.setdefault("MUJOCO_GL", "egl")
