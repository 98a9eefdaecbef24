"""``SynthConfig``: every knob of a synthetic posed RGB-D sequence, validated up front.

Kept apart from the renderer so the scene builder, the trajectory and the CLI can share it
without importing each other.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from ...camera import PinholeCamera

PARALLAX_MODES = ('high', 'low')
#: Camera motions: ``parallax`` = the ``parallax`` mode's trajectory; the others are the
#: stress motions of ``motions.py`` (fixed per-frame translation and rotation steps).
MOTIONS = ('parallax', 'rotation_sweep', 'keyframe_stream', 'forward')
#: Whose poses the pipeline is given (``SynthConfig.pose_frame``).
POSE_FRAMES = ('optical', 'body', 'inverted')

#: Focal length at 640x480 (Kinect-like); other sizes scale it.
DEFAULT_FOCAL_640 = 525.0


@dataclass(frozen=True)
class SynthConfig:
    """A synthetic sequence: same config (seed included) -> bit-identical output."""

    width: int = 640
    height: int = 480
    frames: int = 100
    fps: float = 30.0
    seed: int = 0
    #: 'high': mostly lateral translation (a ``sweep`` m sideways pass, gentle look-at);
    #: 'low': mostly rotation with a few cm of translation.
    parallax: str = 'high'
    #: Focal lengths in pixels; ``None`` = 525 scaled to the image size.
    fx: float | None = None
    fy: float | None = None
    #: Std of the per-frame Gaussian sensor noise, grey levels (0..255).
    noise_sigma: float = 1.5
    #: Fraction of surface groups (walls, boxes, table parts) with a flat albedo.
    textureless_fraction: float = 0.35
    #: Nominal room size (x width, y depth, z height) in metres, before per-seed jitter.
    room_size: tuple[float, float, float] = (5.0, 4.5, 2.7)
    #: Relative per-seed jitter of each room dimension (0.15 = +-15 %).
    room_jitter: float = 0.15
    boxes: int = 6
    tables: int = 2
    #: Lateral sweep length of the 'high' trajectory in metres; ``None`` = random in [0.6, 1.2].
    sweep: float | None = None
    #: Supersample pixels on depth/surface edges (4 extra rays each) so silhouettes do not alias.
    antialias: bool = True
    #: Stamp of the first frame (s); frame ``i`` is at ``t0 + i / fps`` rounded to 1 us.
    t0: float = 1000.0
    #: Camera motion (see :data:`MOTIONS`); the stress motions use the two steps below.
    motion: str = 'parallax'
    #: Stress motions: translation (m) and rotation (degrees) from one frame to the next.
    step_translation: float = 0.012
    step_rotation_deg: float = 0.6
    #: Contrast of the textured albedos around their mean (1 = as drawn; 0.2 = faint texture).
    texture_contrast: float = 1.0
    #: Relative error of the focal lengths *given to the pipeline* (camera.yaml, ``Sequence.camera``);
    #: rendering always uses the true ones (``camera()``). 0.1 = the pipeline's fx, fy are 10 % long.
    focal_error: float = 0.0
    #: Std of a per-frame jitter of the poses *given to the pipeline* (groundtruth.txt,
    #: ``Frame.pose``): translation in metres and rotation in degrees, independent per frame
    #: (a SLAM or odometry source's frame-to-frame noise); rendering and the ground-truth depth
    #: always use the true poses. 0 = exact poses.
    pose_noise_m: float = 0.0
    pose_noise_deg: float = 0.0
    #: The poses *given to the pipeline* are the true ones turned by this many degrees about the
    #: camera's x axis (``T_told = T_true @ R_x``): a camera mounted tilted against the pose
    #: frame it is told (a measured ``camera_from_pose_frame``, a hand-eye calibration). 0 = as told.
    mount_tilt_deg: float = 0.0
    #: Whose poses the pipeline is given: 'optical', the camera's own (x right, y down, z
    #: forward), or 'body', those of a REP 103 body frame holding it (x forward, y left, z up:
    #: ``T_told = T_true @ M^-1`` with ``M`` the camera in the body), with no word of it, as a
    #: robot's odometry published without ``camera_from_pose_frame`` gives them; or 'inverted',
    #: the camera's poses inverted (the world's pose in the camera, T_cw, as a SLAM system keeps
    #: it and a relay may publish it: ``multiview/pose_inversion.py``).
    pose_frame: str = 'optical'
    #: The positions *given to the pipeline* (groundtruth.txt) and the depth images are in a
    #: unit of ``1 / pose_scale`` metres: positions and depths times this, as a monocular SLAM
    #: gives them (its unit is what its initialisation chose). The images are rendered in
    #: metres, so a metric network still reads metres (``fusion/stream_scale.py``). 1 = metres.
    pose_scale: float = 1.0
    #: The poses *given to the pipeline* are the true ones this many seconds later (a pose
    #: source whose clock runs ahead of the camera's, or a camera stamp taken late; negative:
    #: the other way), constant-velocity between neighbouring frames: a time offset between
    #: camera and pose source. At most one frame period either way. 0 = in sync.
    pose_time_offset: float = 0.0
    #: Shutter time (s): each image averages the scene over this interval centred on its stamp,
    #: so a moving camera blurs it along the motion (0 = an instantaneous, sharp image). At most
    #: one frame period, what a dim room gives a 30 Hz camera.
    exposure_time: float = 0.0
    #: Rolling shutter (s): the rows are read out top to bottom over this interval centred on
    #: the stamp, each at its own pose, so a moving camera skews the image (most CMOS colour
    #: cameras; 0 = a global shutter). At most one frame period.
    readout_time: float = 0.0
    #: Renders over ``exposure_time`` and ``readout_time`` (evenly spaced poses along the motion).
    blur_samples: int = 7
    #: Std of each frame's log gain (auto-exposure): frame ``i`` is ``exp(gain_sigma * n_i)``
    #: times as bright (``n_i`` standard normal, drawn per frame), clipped at 255 like a sensor.
    #: 0 = the same exposure for every frame.
    gain_sigma: float = 0.0
    #: Person-sized boxes walking back and forth across the view (``walkers.py``): a world
    #: that is not static, as a robot's camera sees people go by. 0 = a static room.
    walkers: int = 0
    #: Walking speed of the walkers (m/s).
    walker_speed: float = 1.0
    #: Repetitive texture (m): every textured material is one random motif repeated on a square
    #: lattice of about this period (tiles, bricks, shelves, a keyboard), so an epipolar search
    #: finds the same patch again every period. 0 = the aperiodic patterns of ``texture.py``.
    texture_period: float = 0.0
    #: Hand shake (``shake.py``): every pose (true and told) moves by 1-4 Hz sinusoids of this
    #: standard deviation per camera axis, in metres and degrees: a hand-held camera whose speed
    #: and turn rate change every few hundred milliseconds. 0 = the smooth path.
    shake_m: float = 0.0
    shake_deg: float = 0.0
    #: Radial distortion of the true lens (plumb_bob ``k1``, normalised coordinates: a point at
    #: slope radius ``r`` is imaged at ``r (1 + k1 r^2)``; negative = barrel). Images and depth
    #: are rendered through it; camera.yaml says no distortion, as for a camera whose
    #: calibration left its lens out. 0 = a pinhole lens.
    lens_k1: float = 0.0

    def __post_init__(self) -> None:
        def bad(name: str, why: str) -> ValueError:
            return ValueError(f'SynthConfig.{name}={getattr(self, name)!r}: {why}')

        if self.width < 8 or self.height < 8:
            raise bad('width', f'image must be at least 8x8, got {self.width}x{self.height}')
        if self.frames < 1:
            raise bad('frames', 'need at least one frame')
        if not self.fps > 0:
            raise bad('fps', 'must be positive')
        if self.parallax not in PARALLAX_MODES:
            raise bad('parallax', f'expected one of {", ".join(PARALLAX_MODES)}')
        for name in ('fx', 'fy'):
            value = getattr(self, name)
            if value is not None and not value > 0:
                raise bad(name, 'focal length must be positive')
        if not 0 <= self.noise_sigma <= 50:
            raise bad('noise_sigma', 'expected 0..50 grey levels')
        if not 0 <= self.textureless_fraction <= 1:
            raise bad('textureless_fraction', 'expected a fraction in [0, 1]')
        if len(self.room_size) != 3 or min(self.room_size) < 2.2 or max(self.room_size) > 20:
            raise bad('room_size', 'expected three dimensions between 2.2 and 20 m')
        if not 0 <= self.room_jitter < 0.5:
            raise bad('room_jitter', 'expected 0 <= jitter < 0.5')
        if not 0 <= self.boxes <= 40 or not 0 <= self.tables <= 10:
            raise bad('boxes', f'expected 0..40 boxes and 0..10 tables, got {self.boxes} and {self.tables}')
        if self.sweep is not None and not 0 < self.sweep <= 3.0:
            raise bad('sweep', 'expected a lateral sweep in (0, 3] m')
        if self.seed < 0:
            raise bad('seed', 'must be non-negative')
        if self.motion not in MOTIONS:
            raise bad('motion', f'expected one of {", ".join(MOTIONS)}')
        if not 0 <= self.step_translation <= 1.0:
            raise bad('step_translation', 'expected 0..1 m per frame')
        if not 0 <= self.step_rotation_deg <= 30.0:
            raise bad('step_rotation_deg', 'expected 0..30 degrees per frame')
        if not 0 < self.texture_contrast <= 1.0:
            raise bad('texture_contrast', 'expected a contrast in (0, 1]')
        if not -0.5 < self.focal_error < 0.5:
            raise bad('focal_error', 'expected a relative error in (-0.5, 0.5)')
        if not 0 <= self.pose_noise_m <= 0.5:
            raise bad('pose_noise_m', 'expected a translation std of 0..0.5 m')
        if not 0 <= self.pose_noise_deg <= 10.0:
            raise bad('pose_noise_deg', 'expected a rotation std of 0..10 degrees')
        if not -10.0 <= self.mount_tilt_deg <= 10.0:
            raise bad('mount_tilt_deg', 'expected a tilt of -10..10 degrees')
        if self.pose_frame not in POSE_FRAMES:
            raise bad('pose_frame', f'expected one of {", ".join(POSE_FRAMES)}')
        if not 0.05 <= self.pose_scale <= 1.0:
            raise bad('pose_scale', 'expected 0.05..1 (a unit of 1..20 m; depth PNGs hold 13 units)')
        if not abs(self.pose_time_offset) * self.fps <= 1.0:
            raise bad('pose_time_offset', f'expected at most one frame period (1 / fps = {1 / self.fps:g} s)')
        if not 0 <= self.exposure_time * self.fps <= 1.0:
            raise bad('exposure_time', f'expected 0 to one frame period (1 / fps = {1 / self.fps:g} s)')
        if not 0 <= self.readout_time * self.fps <= 1.0:
            raise bad('readout_time', f'expected 0 to one frame period (1 / fps = {1 / self.fps:g} s)')
        if not 2 <= self.blur_samples <= 64:
            raise bad('blur_samples', 'expected 2..64 renders per blurred image')
        if not 0 <= self.gain_sigma <= 1.0:
            raise bad('gain_sigma', 'expected a log-gain std of 0..1')
        if not 0 <= self.walkers <= 4:
            raise bad('walkers', 'expected 0..4 walkers')
        if not 0 < self.walker_speed <= 5.0:
            raise bad('walker_speed', 'expected a walking speed in (0, 5] m/s')
        if not 0 <= self.shake_m <= 0.05 or not 0 <= self.shake_deg <= 5.0:
            raise bad('shake_m', 'expected a shake of 0..0.05 m and 0..5 degrees (std per axis)')
        if not -0.4 <= self.lens_k1 <= 0.4:
            raise bad('lens_k1', 'expected a radial distortion k1 of -0.4..0.4')
        if not (self.texture_period == 0 or 0.02 <= self.texture_period <= 0.5):
            raise bad('texture_period', 'expected 0 (aperiodic) or a period of 0.02..0.5 m')

    def camera(self) -> PinholeCamera:
        """Intrinsics: principal point at the image centre ((W - 1) / 2 with pixel-centre
        coordinates), focal lengths as configured or 525 scaled from 640x480."""
        fx = self.fx if self.fx is not None else DEFAULT_FOCAL_640 * self.width / 640.0
        fy = self.fy if self.fy is not None else DEFAULT_FOCAL_640 * self.height / 480.0
        return PinholeCamera(self.width, self.height, fx, fy, (self.width - 1) / 2.0, (self.height - 1) / 2.0)

    def pipeline_camera(self) -> PinholeCamera:
        """The intrinsics the pipeline is told (camera.yaml): the true ones with the focal
        lengths off by ``focal_error``, the failure of a wrong calibration."""
        true = self.camera()
        if self.focal_error == 0.0:
            return true
        k = 1.0 + self.focal_error
        return PinholeCamera(true.width, true.height, true.fx * k, true.fy * k, true.cx, true.cy)

    def stamp(self, index: int) -> float:
        """Stamp of frame ``index`` rounded to the microsecond, so it survives TUM text files."""
        return round(self.t0 + index / self.fps, 6)

    def as_dict(self) -> dict:
        d = asdict(self)
        d['room_size'] = list(self.room_size)
        return d

    def cli_args(self) -> list[str]:
        """``depth-fusion synth`` options that reproduce this config (the seed, then the
        options that differ from the defaults)."""
        default = SynthConfig()
        args: list[str] = []
        for f in fields(self):
            value, ref = getattr(self, f.name), getattr(default, f.name)
            if value == ref and f.name != 'seed':
                continue
            flag = '--' + f.name.replace('_', '-')
            if isinstance(value, bool):
                args.append(flag if value else f'--no-{f.name.replace("_", "-")}')
            elif isinstance(value, tuple):
                args += [flag, *(repr(float(x)) for x in value)]
            else:
                args += [flag, repr(value) if isinstance(value, float) else str(value)]
        return args
