"""The simulator side of twist: tasks, domain randomisation, backgrounds, rendering, rollouts,
vector environments, re-rendering D from its physics and the Gymnasium environments. It needs
MuJoCo and dm_control; ``twist_data`` reads, writes, verifies and exports D without them."""

import os

# Offscreen rendering must work on headless machines, and MuJoCo picks its GL backend when it is
# first imported: default to EGL unless the user chose a backend.
os.environ.setdefault("MUJOCO_GL", "egl")
