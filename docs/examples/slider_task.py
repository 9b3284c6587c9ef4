"""A task of your own: a block on a rail pushed towards a target (registered on import)."""

import collections

from dm_control import mujoco
from dm_control.rl import control
from dm_control.suite import base

from twist_sim.tasks import TaskSpec, register_task

SCENE = """<mujoco><asset><material name="self" rgba=".8 .5 .2 1"/>
  <material name="grid" rgba=".2 .3 .4 1"/><material name="target" rgba=".9 .1 .1 1"/></asset>
  <worldbody><light pos="0 0 3"/><camera name="side" pos="0 -1.2 .3" xyaxes="1 0 0 0 .2 1"/>
    <geom type="plane" size="2 2 .1" material="grid"/>
    <site name="target" pos=".3 0 .05" size=".03" material="target"/>
    <body name="block" pos="0 0 .05"><joint name="x" type="slide" axis="1 0 0" damping="1"/>
      <geom type="box" size=".05 .05 .05" material="self" mass=".5"/></body></worldbody>
  <actuator><motor joint="x" gear="4" ctrlrange="-1 1" ctrllimited="true"/></actuator></mujoco>"""


class Slide(base.Task):
    def initialize_episode(self, physics):
        physics.named.data.qpos["x"] = self.random.uniform(-0.4, 0.4)

    def get_observation(self, physics):
        return collections.OrderedDict(position=physics.data.qpos.copy(),
                                       velocity=physics.data.qvel.copy())

    def get_reward(self, physics):
        return float(abs(physics.named.data.qpos["x"][0] - 0.3) < 0.05)


def environment():
    return control.Environment(mujoco.Physics.from_xml_string(SCENE), Slide(random=0),
                               time_limit=10, control_timestep=0.04)


register_task(TaskSpec("slider-reach", environment=environment))
