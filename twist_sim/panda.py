"""The paper's manipulation tasks: a Franka Panda arm pushes a block to a goal marker
(``panda-push``) or grasps it and lifts it 10 cm (``panda-lift``).

The arm has the Panda's kinematics (its seven joints' placements, axes and ranges, as MuJoCo
Menagerie's ``franka_emika_panda`` model gives them) with its links drawn as capsules and boxes
rather than meshes: at 64x64 pixels a mesh adds nothing a policy could see, and the package
ships no asset files. Actions are Cartesian deltas of the gripper, at most 2 cm per agent step
at the ``quick`` preset's action repeat of 4 (0.5 cm per control step of 25 ms), plus, for
lifting, the gripper's opening. The hand is welded, pointing down, to a target body that three
force-limited position servos move (at most :data:`MAX_FORCE` per axis, as a real arm's
controller limits what it presses with); the arm's joints follow the hand (gravity
compensated, held softly towards a ready posture so that the redundant elbow stays put).
Episodes last 600 control steps: 150 agent steps at action repeat 4, as the paper's.

Rewards are dense and computed from privileged state, each term a dm_control ``tolerance``
in [0, 1]: reaching the block, then the block's distance to the goal over 20 cm and over the
last 5 cm (push), or the block's height with both fingers on its sides (lift). Pushing's
fingers are fixed shut; lifting's slide. The materials are named as dm_control's, so that domain
randomisation recolours the robot (``self``), its hand and fingers (``effector``), the block
(``decoration``), the goal marker (``target``) and the table (``grid``).
"""

from __future__ import annotations

import collections
import functools

import numpy as np

#: Seconds per control step, and MuJoCo's time step within it.
CONTROL_STEP = 0.025
PHYSICS_STEP = 0.005
#: Control steps per episode: 150 agent steps at action repeat 4.
EPISODE_STEPS = 600
#: The gripper's move per control step at full action, at most (2 cm per agent step at action
#: repeat 4).
MAX_DELTA = 0.005
#: The most each servo that moves the hand pushes with (N): a hand held back by the block or
#: the table presses with a bounded force. With an unbounded drive (a mocap weld) the fingers
#: sank through a pressed block and carried it off, and a pushing teacher learned to.
MAX_FORCE = 30.0
#: Each control step the servos' set point is put this many times ``MAX_DELTA * action``
#: ahead of the fingertips, so that the hand, held back by its damping and force limit,
#: moves 1.5-2 cm per agent step at full action (tested). The set point follows the hand,
#: not its own last value: the next step depends on the physics state alone.
SET_POINT_LEAD = 1.5
#: Where the gripper's fingertips may go: x, y, z bounds in metres (the table's top is z = 0).
WORKSPACE = np.array([[-0.25, 0.25], [-0.25, 0.25], [0.005, 0.3]])
#: The gripper's start: above the table's centre.
START = np.array([0.0, 0.0, 0.15])
#: Half the block's side, and how far below the hand's frame its fingertips are.
BLOCK_HALF = 0.025
FINGERTIPS = 0.105
#: The Panda's ready posture (its joints 1-7, radians), towards which the arm is held.
READY = (0.0, -0.3, 0.0, -2.2, 0.0, 1.9, 0.785)
#: Success: the block within this distance of the goal (push), or its bottom this high above
#: the table (lift), at the episode's end.
PUSH_TOLERANCE = 0.05
LIFT_HEIGHT = 0.10
#: The most a grasping contact's normal may point along the block's up axis (cos 45°): a
#: finger on the block's side grasps it, one on its top face only presses.
SIDE_CONTACT = float(np.cos(np.pi / 4))

#: The arm's seven links, base to wrist: where each sits in its parent's frame (position and
#: quaternion, as the Panda's joint placements), its joint's range (radians) and the capsule,
#: cylinder for the last, that draws it (from-to in its own frame, radius).
_LINKS = (
    ("0 0 0.333", "1 0 0 0", "-2.8973 2.8973", "0 0 -.25 0 0 0", ".06"),
    ("0 0 0", "1 -1 0 0", "-1.7628 1.7628", "0 0 0 0 -.316 0", ".06"),
    ("0 -0.316 0", "1 1 0 0", "-2.8973 2.8973", "0 0 0 .0825 0 0", ".055"),
    ("0.0825 0 0", "1 1 0 0", "-3.0718 -0.0698", "0 0 0 -.0825 .384 0", ".055"),
    ("-0.0825 0.384 0", "1 -1 0 0", "-2.8973 2.8973", "0 0 -.12 0 0 0", ".05"),
    ("0 0 0", "1 1 0 0", "-0.0175 3.7525", "0 0 0 .088 0 0", ".045"),
    ("0.088 0 0", "1 1 0 0", "-2.8973 2.8973", "0 0 0 0 0 .1", ".045"),
)

#: The hand (at the seventh link's flange, turned 45 degrees) and its two fingers, for lifting
#: each a slide joint of up to 4 cm (:data:`_FINGER_JOINT`); the fingers' faces, the hand and
#: the block are what touch.
_HAND = """
<body name="hand" gravcomp="1" pos="0 0 0.107" quat="0.9238795 0 0 -0.3826834">
  <geom type="box" size=".025 .1 .03" pos="0 0 .03" material="effector" class="touch"/>
  <site name="fingertips" pos="0 0 {fingertips}" size=".005"/>
  <body name="left_finger" gravcomp="1" pos="0 0 0.0584">
    {finger1}
    <geom type="box" size=".01 .01 .025" pos="0 .01 .025" material="effector" class="touch"
          friction="2 .01 .001"/>
  </body>
  <body name="right_finger" gravcomp="1" pos="0 0 0.0584" quat="0 0 0 1">
    {finger2}
    <geom type="box" size=".01 .01 .025" pos="0 .01 .025" material="effector" class="touch"
          friction="2 .01 .001"/>
  </body>
</body>
"""


#: A finger's slide joint (lifting only): pushing's fingers are fixed shut, since sprung
#: fingers let a block pressed from above wedge them apart and be carried off.
_FINGER_JOINT = ('<joint name="finger{}" type="slide" axis="0 1 0" range="0 0.04" damping="10" '
                 'stiffness="0"/>')
#: The fingers' coupling and the gripper's actuator (lifting only).
_GRIPPER = """
  <equality><joint joint1="finger1" joint2="finger2"/></equality>
  <actuator><position name="gripper" joint="finger1" kp="300" ctrlrange="0 0.04"/></actuator>
"""


def arm_xml(lift: bool) -> str:
    """The arm's MJCF: a base, the seven links nested one in the next (each joint held softly
    towards :data:`READY`), and the hand at the end, its fingers sliding only for lifting;
    gravity compensated throughout."""
    inner = _HAND.format(fingertips=FINGERTIPS,
                         **{f"finger{i}": _FINGER_JOINT.format(i) if lift else "" for i in (1, 2)})
    for i, (pos, quat, limits, fromto, radius) in reversed(list(enumerate(_LINKS, 1))):
        shape = "cylinder" if i == len(_LINKS) else "capsule"
        inner = (f'<body name="link{i}" gravcomp="1" pos="{pos}" quat="{quat}">'
                 f'<joint name="joint{i}" springref="{READY[i - 1]}" range="{limits}"/>'
                 f'<geom type="{shape}" fromto="{fromto}" size="{radius}"/>{inner}</body>')
    return ('<body name="link0" pos="-0.55 0 0" childclass="arm" gravcomp="1">'
            f'<geom type="cylinder" size=".07 .07" pos="0 0 .07"/>{inner}</body>')


#: Friction for holding the block up: with MuJoCo's default pyramidal cones its soft contacts
#: let a grasped block creep down the fingers (3 mm per 10 agent steps) until it
#: drops; elliptic cones with a high impedance ratio, MuJoCo's advice for grasping, hold it.
#: Pushing holds nothing and keeps the defaults.
_GRASP_FRICTION = ' cone="elliptic" impratio="10"'

_GOAL = '<site name="goal" type="cylinder" pos=".1 .1 .0005" size=".03 .0005" material="target"/>'

_SCENE = """
<mujoco model="{name}">
  <compiler angle="radian"/>
  <option timestep="{physics_step}"{grasp_friction}/>
  <visual><global offwidth="256" offheight="256"/></visual>
  <default>
    <default class="arm">
      <joint axis="0 0 1" damping="5" stiffness="1" armature="0.1"/>
      <geom material="self" contype="0" conaffinity="0" mass="1"/>
      <default class="touch"><geom contype="1" conaffinity="1" mass=".3"/></default>
    </default>
  </default>
  <asset>
    <material name="self" rgba=".92 .92 .93 1"/>
    <material name="effector" rgba=".25 .25 .25 1"/>
    <material name="decoration" rgba=".95 .8 .1 1"/>
    <material name="target" rgba=".9 .1 .1 1"/>
    <material name="grid" rgba=".55 .45 .35 1"/>
  </asset>
  <worldbody>
    <light name="top" pos="0 0 1.5" dir="0 0 -1" diffuse=".7 .7 .7"/>
    <light name="front" pos=".8 0 .8" dir="-1 0 -1" diffuse=".3 .3 .3"/>
    <!-- 47 degrees down at the table's centre: a move towards the camera (x) moves the
         image three quarters as far as one across it does (at 27 degrees, under half) -->
    <camera name="front" pos=".55 0 .6" xyaxes="0 1 0 -.737154 0 .675725" fovy="45"/>
    <geom name="table" type="box" pos="0 0 -.02" size=".7 .5 .02" material="grid"
          friction="1 .005 .0001"/>
    {arm}
    <body name="block" pos="0 0 {block_half}">
      <freejoint name="block"/>
      <geom name="block" type="box" size="{block_half} {block_half} {block_half}" mass=".1"
            material="decoration" friction="1 .005 .0001" solref=".01 1" solimp=".95 .99 .001"/>
    </body>
    {goal}
    <body name="target" gravcomp="1">
      <joint name="target_x" type="slide" axis="1 0 0"/>
      <joint name="target_y" type="slide" axis="0 1 0"/>
      <joint name="target_z" type="slide" axis="0 0 1"/>
      <inertial pos="0 0 0" mass=".1" diaginertia="1e-4 1e-4 1e-4"/>
    </body>
  </worldbody>
  <equality>
    <weld body1="target" body2="hand" relpose="0 0 0 {hand_quat}" solref=".01 1"/>
  </equality>
  <actuator>
    <position name="move_x" joint="target_x" {servo}/>
    <position name="move_y" joint="target_y" {servo}/>
    <position name="move_z" joint="target_z" {servo}/>
  </actuator>{gripper}
</mujoco>
"""


def scene_xml(lift: bool, hand_quat: tuple[float, ...] | None = None) -> str:
    """The MJCF of one task's scene: the same arm, table and block; the goal marker shown
    only for pushing. The hand's weld holds ``hand_quat`` (default: pointing down)."""
    quat = _hand_down() if hand_quat is None else hand_quat
    return _SCENE.format(name="panda-lift" if lift else "panda-push", physics_step=PHYSICS_STEP,
                         grasp_friction=_GRASP_FRICTION if lift else "", arm=arm_xml(lift),
                         block_half=BLOCK_HALF, goal="" if lift else _GOAL,
                         hand_quat=" ".join(f"{q:.9g}" for q in quat),
                         servo=_SERVO.format(force=MAX_FORCE),
                         gripper=_GRIPPER if lift else "")


#: The hand's servos: stiff and critically damped, each pushing with at most ``force``.
_SERVO = 'kp="10000" dampratio="1" forcelimited="true" forcerange="-{force} {force}"'


@functools.cache
def _hand_down() -> tuple[float, ...]:
    """The hand's orientation (a quaternion) in the arm's ready posture, which points it
    straight down (q2 - q4 - q6 = 0): the one its weld to the target holds."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(scene_xml(False, hand_quat=(1.0, 0.0, 0.0, 0.0)))
    data = mujoco.MjData(model)
    data.qpos[[model.joint(f"joint{i}").qposadr[0] for i in range(1, 8)]] = READY
    mujoco.mj_forward(model, data)
    return tuple(float(q) for q in data.xquat[model.body("hand").id])


def _tolerance(distance: float, margin: float) -> float:
    """1 at zero distance, falling smoothly to 0.1 at ``margin`` (dm_control's ``tolerance``
    with a gaussian sigmoid)."""
    from dm_control.utils import rewards

    return float(rewards.tolerance(distance, bounds=(0.0, 0.0), margin=margin))


@functools.cache
def _task_class():
    """The dm_control task class and environment factory, built on first use so that importing
    this module needs no dm_control."""
    from dm_control.rl import control
    from dm_control.suite import base
    from dm_env import specs

    class PandaTask(base.Task):
        def __init__(self, lift: bool, random: int | np.random.RandomState | None = None):
            super().__init__(random=random)
            self.lift = lift

        def action_spec(self, physics):
            return specs.BoundedArray((4 if self.lift else 3,), np.float64, -1.0, 1.0,
                                      name="gripper move" + (", opening" if self.lift else ""))

        def initialize_episode(self, physics):
            ready = _ready_posture(self.lift)
            physics.named.data.qpos[[f"joint{i}" for i in range(1, 8)]] = ready.arm
            physics.named.data.qpos[list(_TARGET_JOINTS)] = ready.target
            physics.named.data.ctrl[list(_SERVOS)] = ready.set_point
            side = self.random.uniform(-0.15, 0.15, size=2)
            block = np.array([side[0] * 0.8, side[1], BLOCK_HALF])
            physics.named.data.qpos["block"][:3] = block
            physics.named.data.qpos["block"][3:] = (1.0, 0.0, 0.0, 0.0)
            if not self.lift:
                angle = self.random.uniform(-np.pi, np.pi)
                distance = self.random.uniform(0.1, 0.2)
                goal = np.clip(block[:2] + distance * np.array([np.cos(angle), np.sin(angle)]),
                               -0.2, 0.2)
                physics.named.model.site_pos["goal"][:2] = goal
            if self.lift:
                physics.named.data.ctrl["gripper"] = 0.04

        def before_step(self, action, physics):
            action = np.asarray(action, np.float64)
            ids = _scene_ids(self.lift)
            ahead = SET_POINT_LEAD * MAX_DELTA * action[:3]
            moved = np.clip(physics.data.site_xpos[ids.fingertips] + ahead,
                            WORKSPACE[:, 0], WORKSPACE[:, 1])
            physics.data.ctrl[ids.servos] = moved + _HAND_ABOVE
            if self.lift:
                physics.data.ctrl[ids.gripper] = 0.02 * (1.0 + action[3])

        def get_observation(self, physics):
            grip = physics.named.data.site_xpos["fingertips"].copy()
            block = physics.named.data.qpos["block"][:3].copy()
            position = [grip, block]
            velocity = [_site_velocity(physics), physics.named.data.qvel["block"][:3].copy()]
            if self.lift:
                position.insert(1, physics.named.data.qpos["finger1"].copy())
                velocity.insert(1, physics.named.data.qvel["finger1"].copy())
            else:
                position.append(physics.named.model.site_pos["goal"][:2].copy())
            return collections.OrderedDict(position=np.concatenate(position),
                                           velocity=np.concatenate(velocity))

        def get_reward(self, physics):
            grip = physics.named.data.site_xpos["fingertips"]
            block = physics.named.data.xpos["block"]
            reach = _tolerance(float(np.linalg.norm(grip - block)), 0.2)
            if not self.lift:
                away = float(np.linalg.norm(block[:2] - physics.named.model.site_pos["goal"][:2]))
                # The near term pays for the last centimetres, which the far one hardly does
                # (0.87 of it at the success tolerance): without it a teacher brought blocks
                # within 2 cm of the goal and let them end 7 cm off, past it.
                return (0.3 * reach + 0.4 * _tolerance(away, 0.2)
                        + 0.3 * _tolerance(away, PUSH_TOLERANCE))
            grasped = float(_fingers_touch(physics))
            height = block[2] - BLOCK_HALF
            lifted = _tolerance(max(LIFT_HEIGHT - height, 0.0), LIFT_HEIGHT)
            return 0.2 * reach + 0.3 * grasped + 0.5 * grasped * lifted

    def environment(lift: bool):
        from dm_control import mujoco

        physics = mujoco.Physics.from_xml_string(scene_xml(lift))
        return control.Environment(physics, PandaTask(lift, random=0),
                                   time_limit=EPISODE_STEPS * CONTROL_STEP,
                                   control_timestep=CONTROL_STEP)

    return PandaTask, environment


def _site_velocity(physics) -> np.ndarray:
    import mujoco

    velocity = np.zeros(6)
    site = physics.model.name2id("fingertips", "site")
    mujoco.mj_objectVelocity(physics.model.ptr, physics.data.ptr, mujoco.mjtObj.mjOBJ_SITE,
                             site, velocity, 0)
    return velocity[3:].copy()


def _fingers_touch(physics) -> bool:
    """Whether both fingers touch the block on its sides (lifting's scene): a contact whose
    normal, in the block's frame, lies closer to horizontal than :data:`SIDE_CONTACT` allows.
    Fingers pressed onto its top face do not count: a teacher paid for them learned to hold
    the block down rather than lift it."""
    ids = _scene_ids(True)
    contact = physics.data.contact
    pairs = np.stack([contact.geom1, contact.geom2], 1)
    with_block = (pairs == ids.block).any(1)
    up = physics.data.xmat[physics.model.geom_bodyid[ids.block]].reshape(3, 3)[:, 2]
    side = np.abs(contact.frame[:, :3] @ up) < SIDE_CONTACT
    others = pairs[with_block & side].ravel()  # both of each pair with the block
    touched = physics.model.geom_bodyid[others[others != ids.block]]
    return bool(np.isin(ids.fingers, touched).all())


class _SceneIds(collections.namedtuple("_SceneIds",
                                       "fingertips servos gripper block fingers")):
    """Indices into a scene's MuJoCo arrays that every control step uses, looked up once:
    the fingertips' site, the hand's servos (x, y, z), the gripper's actuator (lifting;
    else -1), the block's geom and the fingers' bodies."""


@functools.cache
def _scene_ids(lift: bool) -> _SceneIds:
    import mujoco

    model = mujoco.MjModel.from_xml_string(scene_xml(lift))
    obj = mujoco.mjtObj
    return _SceneIds(mujoco.mj_name2id(model, obj.mjOBJ_SITE, "fingertips"),
                     np.array([mujoco.mj_name2id(model, obj.mjOBJ_ACTUATOR, name)
                               for name in _SERVOS]),
                     mujoco.mj_name2id(model, obj.mjOBJ_ACTUATOR, "gripper"),
                     mujoco.mj_name2id(model, obj.mjOBJ_GEOM, "block"),
                     np.array([mujoco.mj_name2id(model, obj.mjOBJ_BODY, name)
                               for name in ("left_finger", "right_finger")]))


#: The target body's slide joints and the servos that move them, x, y, z; the target sits
#: this far above the fingertips (the hand's frame, pointing down).
_TARGET_JOINTS = ("target_x", "target_y", "target_z")
_SERVOS = ("move_x", "move_y", "move_z")
_HAND_ABOVE = np.array([0.0, 0.0, FINGERTIPS])


class _Ready(collections.namedtuple("_Ready", "arm target set_point")):
    """The arm's joints, the target's joints and the servos' set point, with the gripper
    settled at :data:`START`."""


@functools.cache
def _ready_posture(lift: bool) -> _Ready:
    """Settle the arm once from its ready posture onto the target at :data:`START` (the
    hand pointing down): every episode starts from this instant."""
    import mujoco

    model = mujoco.MjModel.from_xml_string(scene_xml(lift))
    data = mujoco.MjData(model)
    arm = [model.joint(f"joint{i}").qposadr[0] for i in range(1, 8)]
    target = [model.joint(name).qposadr[0] for name in _TARGET_JOINTS]
    servos = [model.actuator(name).id for name in _SERVOS]
    data.qpos[arm] = READY
    mujoco.mj_forward(model, data)
    data.qpos[target] = data.xpos[model.body("hand").id]  # the weld satisfied at the start
    data.ctrl[servos] = START + _HAND_ABOVE
    for _ in range(1500):
        mujoco.mj_step(model, data)
    return _Ready(tuple(float(q) for q in data.qpos[arm]), data.qpos[target].copy(),
                  data.ctrl[servos].copy())


def succeeded(lift: bool, state: np.ndarray) -> bool:
    """Whether an episode ending in privileged state ``state`` [14] succeeded: the block's
    bottom at least :data:`LIFT_HEIGHT` above the table (lift), or its centre within
    :data:`PUSH_TOLERANCE` of the goal (push)."""
    if lift:
        return bool(state[6] - BLOCK_HALF >= LIFT_HEIGHT)
    return bool(np.linalg.norm(state[3:5] - state[6:8]) < PUSH_TOLERANCE)


def environment(lift: bool):
    """A dm_control ``control.Environment`` of ``panda-lift`` (``lift``) or ``panda-push``."""
    return _task_class()[1](lift)
