"""What an episode is, as the bus carries it inside its messages (``ControlRequest.spec``, ``EpisodeEvent.spec``,
``EpisodeScore.spec``): the episode spec, its camera and world, the camera perturbations the noise injector applies
in order (one frozen struct per noise model, in ``NoiseStage`` and ``NOISE_MODELS``), and the bounds and choices
every spec is checked against. The messages that carry a spec are in ``protocol.messages``; the same conventions hold
(SI units and radians, the unit in the field name; camera in the car frame).
"""

from __future__ import annotations

import msgspec

from protocol.suggest import did_you_mean

# Driving directions of an episode round its circuit (``EpisodeSpec.direction``).
DIRECTIONS: tuple[str, ...] = ("forward", "reverse")
RENDERERS: tuple[str, ...] = ("pybullet", "gl", "auto")  # EpisodeSpec.renderer
LOOKS: tuple[str, ...] = ("flat", "gazebo")  # WorldVariation.look
# The renderers that draw each look ("auto" picks gl, and fails the look where it falls back to pybullet).
LOOK_RENDERERS: dict[str, tuple[str, ...]] = {"flat": ("pybullet", "gl", "auto"), "gazebo": ("gl", "auto")}

# Bounds of spec fields, one table for both places that check them: a spec built in code (``__post_init__``, via
# :func:`check_bounds`) and a matrix file (``orchestrator.matrix.schema``, as msgspec constraints at the value's line;
# msgspec applies ``Meta`` only when it converts data, never when a struct is built).
CAMERA_BOUNDS: dict[str, msgspec.Meta] = {
    "width_px": msgspec.Meta(ge=8, le=4096),
    "height_px": msgspec.Meta(ge=8, le=4096),
    "hfov_rad": msgspec.Meta(ge=0.1, le=3.0),
    "near_m": msgspec.Meta(gt=0),
    "far_m": msgspec.Meta(gt=0),
}
SPEC_BOUNDS: dict[str, msgspec.Meta] = {
    "laps": msgspec.Meta(ge=1),
    "max_sim_seconds": msgspec.Meta(gt=0),
    "step_s": msgspec.Meta(ge=0.001, le=1.0),
    "brain_timeout_s": msgspec.Meta(gt=0),
    # Only the lower bound here: the upper one is the circuit's length, checked where the circuit is loaded
    # (``Circuit.check_start_m``).
    "start_m": msgspec.Meta(ge=0),
}


def bound_text(bound: msgspec.Meta) -> str:
    """``within 8..4096``, ``>= 1`` or ``> 0``: a bound as an error message says it."""
    if bound.ge is not None and bound.le is not None:
        return f"within {bound.ge}..{bound.le}"
    limits = [(">=", bound.ge), (">", bound.gt), ("<=", bound.le), ("<", bound.lt)]
    return " and ".join(f"{sign} {value}" for sign, value in limits if value is not None)


class FieldError(ValueError):
    """A struct's value outside its bound; ``field`` names the field, so a caller decides on it, not on the text."""

    def __init__(self, message: str, *, field: str):
        super().__init__(message)
        self.field = field


def check_bounds(struct: msgspec.Struct, bounds: dict[str, msgspec.Meta]) -> None:
    """Raise FieldError naming the first field of ``struct`` outside its bound in ``bounds``."""
    for name, bound in bounds.items():
        value = getattr(struct, name)
        inside = (
            (bound.ge is None or value >= bound.ge)
            and (bound.gt is None or value > bound.gt)
            and (bound.le is None or value <= bound.le)
            and (bound.lt is None or value < bound.lt)
        )
        if not inside:
            raise FieldError(f"{name} must be {bound_text(bound)}, got {value}", field=name)


class WorldVariation(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Visual variations of a circuit's world (Behavior Metrics ships them as separate worlds).

    line: centre line colour, "red", "white" or "none". road: "grey" (asphalt) or "white".
    walls: 0.5 m walls on both road edges; without them grass is seen beyond the road edge.
    lighting: "sun" (flat, bright) or "no_sun" (darker, as BM's *_no_sun worlds).
    look: "flat" (flat colours: the parity reference both renderers draw) or "gazebo" (textured asphalt and grass,
        shading, shadows and a cloudy sky as Behavior Metrics' Gazebo worlds; the gl renderer only).
    """

    line: str = "red"
    road: str = "grey"
    walls: bool = True
    lighting: str = "sun"
    look: str = "flat"

    def __post_init__(self) -> None:
        for field_name, allowed in (
            ("line", ("red", "white", "none")),
            ("road", ("grey", "white")),
            ("lighting", ("sun", "no_sun")),
            ("look", LOOKS),
        ):
            value = getattr(self, field_name)
            if value not in allowed:
                raise ValueError(
                    f"{field_name} must be one of {', '.join(allowed)}, got {value!r}" + did_you_mean(value, allowed)
                )


# -- camera perturbations applied by the noise injector, in order (``EpisodeSpec.noise``) --


class _Noise(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True, tag_field="model"):
    pass


MAX_DELAY_FRAMES = 200  # 10 s at 20 Hz; the injector buffers this many frames
MAX_OCCLUSION_PATCHES = 100


def _check_probability(name: str, value: float) -> None:
    if not 0.0 <= value <= 1.0:
        raise ValueError(f"{name} must be within 0..1, got {value}")


class SaltPepper(_Noise, tag="salt_pepper", frozen=True):
    """Each pixel becomes black or white (equally likely) with ``probability`` (the paper: 0.2, 0.4, 0.6)."""

    probability: float

    def __post_init__(self) -> None:
        _check_probability("salt_pepper probability", self.probability)


class Gaussian(_Noise, tag="gaussian", frozen=True):
    """Additive gaussian noise, standard deviation ``sigma`` in 0-255 intensity units, clipped."""

    sigma: float

    def __post_init__(self) -> None:
        if not 0 <= self.sigma < float("inf"):
            raise ValueError(f"gaussian sigma must be >= 0, got {self.sigma}")


class Blur(_Noise, tag="blur", frozen=True):
    """Gaussian blur with a ``kernel_px`` x ``kernel_px`` kernel (odd)."""

    kernel_px: int

    def __post_init__(self) -> None:
        if self.kernel_px < 1 or self.kernel_px % 2 == 0:
            raise ValueError(f"blur kernel_px must be an odd number >= 1, got {self.kernel_px}")


class Brightness(_Noise, tag="brightness", frozen=True):
    """``out = contrast * (in - 128) + 128 + 255 * brightness``, clipped: brightness -1..1, contrast >= 0."""

    brightness: float = 0.0
    contrast: float = 1.0

    def __post_init__(self) -> None:
        if not (-1.0 <= self.brightness <= 1.0 and 0 <= self.contrast < float("inf")):
            raise ValueError(
                f"brightness must be within -1..1 and contrast >= 0, got {self.brightness}, {self.contrast}"
            )


class Occlusion(_Noise, tag="occlusion", frozen=True):
    """``patches`` black rectangles, each ``size_fraction`` of the image's height by ``size_fraction`` of its width,
    at random places (they may overlap), in a frame with ``probability``."""

    patches: int = 1
    size_fraction: float = 0.2
    probability: float = 1.0

    def __post_init__(self) -> None:
        _check_probability("occlusion probability", self.probability)
        if not 0 <= self.patches <= MAX_OCCLUSION_PATCHES or not 0.0 < self.size_fraction <= 1.0:
            raise ValueError(
                f"occlusion needs patches >= 0 and size_fraction within (0, 1], got {self.patches}, "
                f"{self.size_fraction}"
            )


class Jpeg(_Noise, tag="jpeg", frozen=True):
    """JPEG re-encoding at ``quality`` (1-100)."""

    quality: int

    def __post_init__(self) -> None:
        if not 1 <= self.quality <= 100:
            raise ValueError(f"jpeg quality must be within 1..100, got {self.quality}")


class Delay(_Noise, tag="delay", frozen=True):
    """The brain sees the image of ``frames`` frames earlier (the first frames of an episode: the oldest one)."""

    frames: int

    def __post_init__(self) -> None:
        if not 0 <= self.frames <= MAX_DELAY_FRAMES:
            raise ValueError(f"delay frames must be within 0..{MAX_DELAY_FRAMES}, got {self.frames}")


class Drop(_Noise, tag="drop", frozen=True):
    """A frame is lost with ``probability``: the brain gets no new image and its last command stands."""

    probability: float

    def __post_init__(self) -> None:
        _check_probability("drop probability", self.probability)


# Behavior Metrics' image perturbations (its ``ImageTranform`` options), with BM's parameters, as BM's pinned
# albumentations 1.0.3 draws them (night, daytime and affine through albumentations: ``pip install drivebench[bm]``;
# the others drawn by drivebench). Each is seeded from the episode like every model.


class Rain(_Noise, tag="rain", frozen=True):
    """BM's rain as albumentations 1.0.3 draws it: torrential, H x W // 500 streaks 60 px long (BM's 20 px is
    overridden), all leaning 10 px right, 1 px wide, grey (200, 200, 200), blur 7, HLS lightness x 0.7."""


class Night(_Noise, tag="night", frozen=True):
    """BM's night: brightness -0.5 (of the full range)."""


class Daytime(_Noise, tag="daytime", frozen=True):
    """BM's daytime: brightness +0.3 (of the full range)."""


class Shadow(_Noise, tag="shadow", frozen=True):
    """BM's shadow: 1.0.3's random shadow with its defaults (1-2 pentagons in the lower half, lightness x 0.5)."""


class Snow(_Noise, tag="snow", frozen=True):
    """BM's snow: 1.0.3's random snow with its defaults (lightness under a random threshold x 2.5)."""


class Fog(_Noise, tag="fog", frozen=True):
    """BM's fog: 1.0.3's random fog with its defaults (faint white discs blended from the centre out, blurred)."""


class Sunflare(_Noise, tag="sunflare", frozen=True):
    """BM's sun flare: 1.0.3's random sun flare with its defaults (a 400 px sun in the upper half, 6-10 discs)."""


class Affine(_Noise, tag="affine", frozen=True):
    """BM's affine: the image shifted 10 % of its width to the left (black fill), imitating a camera offset."""


NoiseStage = (
    SaltPepper
    | Gaussian
    | Blur
    | Brightness
    | Occlusion
    | Jpeg
    | Delay
    | Drop
    | Rain
    | Night
    | Daytime
    | Shadow
    | Snow
    | Fog
    | Sunflare
    | Affine
)
BM_NOISE_MODELS: tuple[type[_Noise], ...] = (Rain, Night, Daytime, Shadow, Snow, Fog, Sunflare, Affine)
NOISE_MODELS: tuple[type[_Noise], ...] = (
    SaltPepper,
    Gaussian,
    Blur,
    Brightness,
    Occlusion,
    Jpeg,
    Delay,
    Drop,
    *BM_NOISE_MODELS,
)


class CameraSpec(msgspec.Struct, frozen=True, kw_only=True):
    """The front camera, mounted on the car (car frame: x forward, y left, z up; metres, radians).

    Defaults follow Behavior Metrics' F1 car: 0.45 m ahead of the car origin, 0.10 m high, level, 90 deg horizontal
    field of view, clip planes 0.1-15 m. The vertical field of view follows from the aspect ratio.
    """

    width_px: int = 320
    height_px: int = 240
    hfov_rad: float = 1.57
    forward_m: float = 0.45
    lateral_offset_m: float = 0.0
    height_m: float = 0.10
    pitch_down_rad: float = 0.0
    yaw_rad: float = 0.0
    near_m: float = 0.1
    far_m: float = 15.0

    def __post_init__(self) -> None:
        check_bounds(self, CAMERA_BOUNDS)
        if not 0 < self.near_m < self.far_m:
            raise ValueError(f"need 0 < near_m < far_m, got {self.near_m} and {self.far_m}")


class EpisodeSpec(msgspec.Struct, frozen=True, kw_only=True):
    """Everything that defines one episode; the same spec twice gives identical messages (lock-step).

    circuit: circuit name (``drivebench circuits list``).
    laps: lap target; the episode ends when it is reached.
    max_sim_seconds: simulated-time limit.
    step_s: simulation and control period (Behavior Metrics: 0.05 s, 20 Hz).
    seed: seeds every random generator of the episode.
    realtime: False = lock-step (wait for the brain's answer to every frame); True = free-running at wall-clock
        rate with the latest command.
    active_brain: name of the brain whose commands drive the car.
    brain_timeout_s: lock-step: wall seconds to wait for the answer to one frame before ending the episode.
    world: visual variation of the circuit's world.
    noise: camera perturbations applied in order by the noise injector (empty: brains see ground truth).
    direction: "forward" drives the circuit in its own order (every built-in circuit runs clockwise, seen from
        above, as the paper's recordings did); "reverse" drives it the other way round from the same start point.
    renderer: "pybullet" (TinyRenderer, the reference), "gl" (OpenGL on headless EGL, same scene, ~10x faster) or
        "auto" (gl where an EGL context can be made, else pybullet); the simulator replaces "auto" by its choice in
        the spec it publishes, so scores and recordings name the renderer that drew the frames.
    start_m: where the car starts, in metres along the circuit in driving order (so from the start line the other
        way round when ``direction`` is "reverse"), on the centre line facing the driving direction; 0 = the start
        line. Within [0, the circuit's length). Progress, laps and lap times are measured from there: a lap is the
        circuit's length driven back to that point. The rendered world is the same wherever the car starts.
    """

    circuit: str = "simple"
    laps: int = 1
    max_sim_seconds: float = 300.0
    step_s: float = 0.05
    seed: int = 0
    realtime: bool = False
    camera: CameraSpec = CameraSpec()
    active_brain: str = "explicit"
    brain_timeout_s: float = 10.0
    world: WorldVariation = WorldVariation()
    noise: list[NoiseStage] = []
    direction: str = "forward"
    renderer: str = "pybullet"
    start_m: float = 0.0

    def __post_init__(self) -> None:
        if self.renderer not in RENDERERS:
            raise FieldError(f"renderer must be one of {', '.join(RENDERERS)}, got {self.renderer!r}", field="renderer")
        if self.direction not in DIRECTIONS:
            raise FieldError(
                f"direction must be one of {', '.join(DIRECTIONS)}, got {self.direction!r}", field="direction"
            )
        check_bounds(self, SPEC_BOUNDS)

    @property
    def step_ns(self) -> int:
        return round(self.step_s * 1e9)
