"""Fast K-view domain-randomised rendering of a physics state (headless, CPU-friendly).

Design (measured on a 2-core machine with Mesa llvmpipe; see docs/performance.md,
"Rendering"): dm_control's ``physics.render`` spends almost all its time on a 2048² shadow map,
4x multisampling, the floor's mirror reflection and finely tessellated capsules, of which
only the multisampling shows at 64x64, on thin geoms (cartpole's pole and rails, the cup's
string: they alias into stray pixels). ``supersample`` brings that back by rendering
``supersample``² times the pixels and area-averaging them (about half the speed at 2).
This renderer owns a private copy of the task's model with shadows, multisampling and
reflection off and capsule tessellation reduced (12 slices, 6 stacks: the
silhouettes are pixel-identical at 64x64 to the default 28x16 in our comparisons), draws the K
views side by side into one offscreen framebuffer and reads them back with one
``mjr_readPixels``.

Backgrounds are not uploaded as skybox textures (a texture upload per frame costs more than the
render). The sky is switched off so background pixels keep the cleared depth of 1.0, and a
crop of the chosen texture is composited into exactly those pixels; objects, floor and lighting
stay MuJoCo's. Colours, light intensity and camera pose are applied to the model/scene between
``mjv_updateScene`` and ``mjr_render``, which costs microseconds.

Given the same physics vector and parameters a frame is pixel-identical on the same machine and
library versions, which is what ``twist-data render`` and ``verify --rerender`` rely on.
"""

from __future__ import annotations

import atexit
import contextlib
import copy
import functools
import logging
import math
import os
import weakref
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Protocol

import cv2
import numpy as np

from twist_data.errors import ConfigError
from twist_sim.backgrounds import BackgroundBank, directory_bank, procedural_bank
from twist_sim.errors import RenderUnavailableError
from twist_sim.randomisation import COLOUR_GROUPS, VIEW_PARAMS, DRConfig, DRSampler
from twist_sim.tasks import TaskSpec, load_environment, model_rows, restore_physics, task_spec

log = logging.getLogger(__name__)

#: Capsule/sphere tessellation used for rendering (dm_control's default is 28 slices, 16 stacks).
RENDER_SLICES = 12
RENDER_STACKS = 6
_MAX_FRAMEBUFFER = 2048


def load_task_model(spec: TaskSpec):
    """The task's compiled MuJoCo model, as dm_control builds it (no simulation state)."""
    return load_environment(spec).physics.model.ptr


def camera_pose(model: Any, camera: int) -> dict[str, Any]:
    """Where a model's ``camera`` sits on its body (position, quaternion) and its vertical
    field of view in degrees: what a render block records, so that frames are never
    re-rendered from a scene whose camera has since moved."""
    return {"pos": model.cam_pos[camera].tolist(), "quat": model.cam_quat[camera].tolist(),
            "fovy": float(model.cam_fovy[camera])}


def background_bank(config: DRConfig, texture_size: int) -> BackgroundBank | None:
    """The bank a config draws backgrounds from (``None`` for ``background="none"``)."""
    if config.background == "none":
        return None
    if config.background == "directory":
        return directory_bank(Path(config.background_dir), texture_size)
    return procedural_bank(config.background, config.background_count, texture_size,
                           config.background_seed)


#: Renderers whose GL context is still open. A context left to MuJoCo's own destructor at
#: interpreter shutdown, after EGL is torn down, prints an EGLError traceback from a user's
#: script that never called close(); these are closed at exit instead, while EGL still works.
_OPEN: weakref.WeakSet[DRRenderer] = weakref.WeakSet()


def _close_open_renderers() -> None:
    for renderer in list(_OPEN):
        with contextlib.suppress(Exception):
            renderer.close()


def _track(renderer: DRRenderer) -> None:
    # Registered after MuJoCo registers its eglTerminate (at the first context), so that it
    # runs before it: atexit calls the last registered first.
    if not _OPEN:
        atexit.unregister(_close_open_renderers)
        atexit.register(_close_open_renderers)
    _OPEN.add(renderer)


#: Where MuJoCo's scene takes the cameras and lights from: a tracking camera's pose, and a
#: tracking light's, follow the body in ``mj_forward``.
_FRAMING = ("cam_xpos", "cam_xmat", "light_xpos", "light_xdir")


class FrameRenderer(Protocol):
    """What recording needs of a renderer: :class:`DRRenderer` (in-process) or
    :class:`twist_sim.render_process.RenderProcess` (a child process, pipelined)."""

    views: int
    image_size: int

    def sampler(self, seed: int = 0) -> DRSampler: ...

    def provenance(self, first_view: int = 0) -> dict[str, Any]: ...

    def submit(self, physics: np.ndarray, params: Mapping[str, np.ndarray]) -> None: ...

    def gather(self) -> np.ndarray: ...


class DRRenderer:
    """Renders K domain-randomised views of one task's physics states.

    Use as a context manager, or call :meth:`close`, to free the GL context.
    """

    def __init__(self, task: str, config: DRConfig, image_size: int = 64, views: int = 2,
                 supersample: int = 1, states: int = 1) -> None:
        if image_size < 1:
            raise ConfigError(f"image_size must be a positive number of pixels, got {image_size}")
        if views < 1:
            raise ConfigError(f"views (K) must be >= 1, got {views}")
        if supersample < 1:
            raise ConfigError(f"supersample must be >= 1, got {supersample}")
        if states < 1:
            raise ConfigError(f"states must be >= 1, got {states}")
        import mujoco

        self._mj = mujoco
        self.spec = task_spec(task)
        self.config = config
        self.image_size = image_size
        self.views = views
        self.states = states
        self.supersample = supersample
        side = image_size * supersample
        self._side = side
        # Backgrounds are twice the render size so that random crops move the texture around.
        self.bank = background_bank(config, 2 * side)
        self.max_offset = side if self.bank is not None else 0

        self.model = copy.copy(load_task_model(self.spec))
        m = self.model
        m.vis.quality.shadowsize = 0
        m.vis.quality.offsamples = 0
        m.vis.quality.numslices = RENDER_SLICES
        m.vis.quality.numstacks = RENDER_STACKS
        tiles = states * views
        self._cols = max(1, min(tiles, _MAX_FRAMEBUFFER // side))
        self._rows = math.ceil(tiles / self._cols)
        if self._rows * side > _MAX_FRAMEBUFFER:
            raise ConfigError(f"states x views x image size do not fit a {_MAX_FRAMEBUFFER}² "
                              f"framebuffer: {states} states, K={views}, image size "
                              f"{image_size}, supersample {supersample}")
        m.vis.global_.offwidth = self._cols * side
        m.vis.global_.offheight = self._rows * side
        self.data = mujoco.MjData(m)
        self._task_rows = model_rows(m, self.spec)
        self._groups = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_MATERIAL, g) for g in COLOUR_GROUPS]
        self.nominal_colours = np.array(
            [m.mat_rgba[g, :3] if g >= 0 else (0.5, 0.5, 0.5) for g in self._groups], np.float32)
        self._gl = self._make_context(self._cols * side, self._rows * side)
        _track(self)
        self._context = mujoco.MjrContext(m, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._context)
        self._scene = mujoco.MjvScene(m, maxgeom=1000)
        for flag in ("mjRND_SHADOW", "mjRND_REFLECTION", "mjRND_HAZE"):
            self._scene.flags[getattr(mujoco.mjtRndFlag, flag)] = 0
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._camera.fixedcamid = self.spec.camera
        self._rgb = np.empty((self._rows * side, self._cols * side, 3), np.uint8)
        self._depth = np.empty((self._rows * side, self._cols * side), np.float32)
        self._submitted: list[np.ndarray] = []

    def _make_context(self, width: int, height: int):
        try:
            context = self._mj.GLContext(width, height)
            context.make_current()
        except Exception as exc:  # the GL backends raise assorted types
            backend = os.environ.get("MUJOCO_GL", "(unset)")
            raise RenderUnavailableError(
                f"cannot create an offscreen OpenGL context with MUJOCO_GL={backend}: {exc}"
            ) from exc
        return context

    # -- parameters --------------------------------------------------------------------------
    @functools.cached_property
    def background_colours(self) -> np.ndarray | None:
        """The bank's colour grid when the config camouflages bodies, else ``None``."""
        if self.bank is None or self.config.low_contrast_share == 0:
            return None
        return self.bank.colour_grid()

    def sampler(self, seed: int = 0) -> DRSampler:
        """A parameter sampler matched to this renderer's bank, nominal colours and K."""
        return DRSampler(self.config, self.nominal_colours, self.views,
                         len(self.bank) if self.bank is not None else 0, self.max_offset, seed,
                         self.background_colours)

    def provenance(self, first_view: int = 0) -> dict[str, Any]:
        """The render block a dataset records (``spec.extra['render']``) to reproduce these
        renders when they occupy views ``first_view`` .. ``first_view + K``."""
        bank = None
        if self.bank is not None:
            bank = {"source": self.bank.source, "count": len(self.bank), "size": self.bank.size,
                    "sha256": self.bank.digest(), "names": list(self.bank.names)}
        return {"views": [first_view, first_view + self.views],
                "config": self.config.to_json(), "image_size": self.image_size,
                "supersample": self.supersample, "camera": self.spec.camera,
                "camera_pose": camera_pose(self.model, self.spec.camera),
                "slices": RENDER_SLICES, "stacks": RENDER_STACKS, "bank": bank}

    def gl_info(self) -> dict[str, str]:
        """The OpenGL implementation that draws this renderer's frames (``gl_vendor``,
        ``gl_renderer``, ``gl_version``): frames are bit-identical only under the same one, so
        a dataset records it beside its library versions. Empty where it cannot be read."""
        try:
            self._gl.make_current()
            from OpenGL import GL

            return {f"gl_{name.lower()}": GL.glGetString(getattr(GL, f"GL_{name}")).decode()
                    for name in ("VENDOR", "RENDERER", "VERSION")}
        except Exception:  # PyOpenGL absent, or another platform binding than the context's
            return {}

    # -- rendering ---------------------------------------------------------------------------
    def render(self, physics: np.ndarray, params: Mapping[str, np.ndarray],
               out: np.ndarray | None = None) -> np.ndarray:
        """Render the K views of ``physics`` under ``params`` ({name: [K, ...]}) -> [K, H, W, 3]."""
        return self.render_states([physics], [params], out=None if out is None else out[None])[0]

    def render_states(self, physics: Sequence[np.ndarray],
                      params: Sequence[Mapping[str, np.ndarray]],
                      places: Sequence[int] | None = None,
                      out: np.ndarray | None = None,
                      framed_by: Sequence[np.ndarray] | None = None) -> np.ndarray:
        """Render the K views of several physics states, state i under ``params[i]`` in place
        ``places[i]`` (default i) of the ``states`` the framebuffer holds, and read them
        back at once -> [N, K, H, W, 3]. A batch of environments so saves N - 1 read-backs,
        each of which waits for the GPU to finish drawing. With ``framed_by``, state i is
        seen from where the camera and lights stood in physics ``framed_by[i]``: a tracking
        camera held still, which shows the body's motion between the two (not what acting
        sees, whose camera follows; research/probes/pair_speed.py compares both).

        A frame depends on its place by at most one level in a few pixels (the rasteriser
        rounds at another offset): a state drawn in the same place is pixel-identical to
        :meth:`render` of it alone in place 0 (tested)."""
        mj, m, side = self._mj, self.model, self._side
        n, k = len(physics), self.views
        places = list(range(n)) if places is None else [int(p) for p in places]
        if len(params) != n or len(places) != n or n == 0:
            raise ConfigError(f"render_states needs one parameter set and place per state, "
                              f"got {n} states, {len(params)} sets, {len(places)} places")
        if min(places) < 0 or max(places) >= self.states or len(set(places)) != n:
            raise ConfigError(f"render_states places must be distinct and in [0, "
                              f"{self.states}), got {places}")
        if framed_by is not None and len(framed_by) != n:
            raise ConfigError(f"render_states needs one framing physics per state, got "
                              f"{len(framed_by)} for {n} states")
        checked = [self._check_params(p) for p in params]
        self._gl.make_current()
        for i in range(n):
            if framed_by is not None:
                restore_physics(m, self.data, framed_by[i], self._task_rows, self.spec.name)
                frame = [getattr(self.data, f).copy() for f in _FRAMING]
            restore_physics(m, self.data, physics[i], self._task_rows, self.spec.name)
            if framed_by is not None:
                for name, value in zip(_FRAMING, frame, strict=True):
                    getattr(self.data, name)[:] = value
            for v in range(k):
                for row, group in enumerate(self._groups):
                    if group >= 0:
                        m.mat_rgba[group, :3] = checked[i]["colour"][v, row]
                self._scene.flags[mj.mjtRndFlag.mjRND_SKYBOX] = int(checked[i]["background"][v]) < 0
                mj.mjv_updateScene(m, self.data, self._option, self._perturb, self._camera,
                                   mj.mjtCatBit.mjCAT_ALL, self._scene)
                self._adjust_scene(float(checked[i]["light"][v]), checked[i]["camera_shift"][v],
                                   checked[i]["camera_rotation"][v])
                r, c = divmod(places[i] * k + v, self._cols)
                viewport = mj.MjrRect(c * side, (self._rows - 1 - r) * side, side, side)
                mj.mjr_render(viewport, self._scene, self._context)
        # Tile row r lies at the top of the framebuffer: read only the rows drawn.
        drawn = math.ceil((max(places) + 1) * k / self._cols)
        rgb, depth = self._rgb[:drawn * side], self._depth[:drawn * side]
        mj.mjr_readPixels(rgb, depth, mj.MjrRect(0, (self._rows - drawn) * side,
                                                 self._cols * side, drawn * side), self._context)
        if out is None:
            out = np.empty((n, k, self.image_size, self.image_size, 3), np.uint8)
        rgb, depth = rgb[::-1], depth[::-1]  # OpenGL rows run bottom-up
        for i in range(n):
            for v in range(k):
                r, c = divmod(places[i] * k + v, self._cols)
                tile = (slice(r * side, (r + 1) * side), slice(c * side, (c + 1) * side))
                # Composite in the readback buffer itself: it is rewritten by every render.
                view = rgb[tile]
                background = int(checked[i]["background"][v])
                if background >= 0:
                    y, x = (int(o) for o in checked[i]["background_offset"][v])
                    # copyto with a mask is ~3x faster here than boolean-index assignment.
                    np.copyto(view, self.bank.textures[background, y:y + side, x:x + side],
                              where=(depth[tile] >= 1.0)[..., None])
                if self.supersample > 1:
                    out[i, v] = cv2.resize(view, (self.image_size, self.image_size),
                                           interpolation=cv2.INTER_AREA)
                else:
                    out[i, v] = view
        return out

    def submit(self, physics: np.ndarray, params: Mapping[str, np.ndarray]) -> None:
        """Render now and keep the frames for :meth:`gather` (the in-process twin of
        :meth:`twist_sim.render_process.RenderProcess.submit`)."""
        self._submitted.append(self.render(physics, params))

    def gather(self) -> np.ndarray:
        """Every frame submitted since the last gather, in order: [T, K, H, W, 3] uint8."""
        side = self.image_size
        frames = (np.stack(self._submitted) if self._submitted
                  else np.empty((0, self.views, side, side, 3), np.uint8))
        self._submitted = []
        return frames

    def _adjust_scene(self, light: float, shift: np.ndarray, rotation: np.ndarray) -> None:
        scene = self._scene
        if light != 1.0:
            for i in range(scene.nlight):
                lamp = scene.lights[i]
                lamp.ambient[:] = np.asarray(lamp.ambient) * light
                lamp.diffuse[:] = np.asarray(lamp.diffuse) * light
                lamp.specular[:] = np.asarray(lamp.specular) * light
        if np.any(shift) or np.any(rotation):
            turn = cv2.Rodrigues(np.asarray(rotation, np.float64).reshape(3, 1))[0]
            for eye in scene.camera:
                eye.pos[:] = np.asarray(eye.pos) + shift
                eye.forward[:] = turn @ np.asarray(eye.forward)
                eye.up[:] = turn @ np.asarray(eye.up)

    def _check_params(self, params: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        checked = {}
        for p in VIEW_PARAMS:
            if p.name not in params:
                raise ConfigError(f"DR parameters lack {p.name!r}; expected {[q.name for q in VIEW_PARAMS]}")
            value = np.asarray(params[p.name])
            if value.shape != (self.views, *p.shape):
                raise ConfigError(f"DR parameter {p.name!r} must have shape "
                                  f"{(self.views, *p.shape)}, got {value.shape}")
            checked[p.name] = value
        background = checked["background"]
        n = len(self.bank) if self.bank is not None else 0
        if np.any(background >= n) or np.any(background < -1):
            raise ConfigError(f"background index out of range [-1, {n}): {background.tolist()}")
        offset = checked["background_offset"]
        if np.any(offset < 0) or np.any(offset > self.max_offset):
            raise ConfigError(f"background_offset must be in [0, {self.max_offset}], "
                              f"got {offset.tolist()}")
        return checked

    # -- lifetime ----------------------------------------------------------------------------
    def close(self) -> None:
        if self._gl is not None:
            # GL object names are per context: freed while another renderer's context is
            # current, they would delete that renderer's framebuffers and textures instead.
            self._gl.make_current()
            self._context.free()
            self._gl.free()
            self._gl = None

    def __enter__(self) -> DRRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        # At interpreter shutdown the GL library may already be gone.
        with contextlib.suppress(Exception):
            self.close()
