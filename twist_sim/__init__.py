"""The simulator side of twist: tasks, domain randomisation, backgrounds, rendering, rollouts,
vector environments, re-rendering D from its physics and the Gymnasium environments. It needs
MuJoCo and dm_control; ``twist_data`` reads, writes, verifies and exports D without them."""
