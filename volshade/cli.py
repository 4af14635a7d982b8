"""The ``volshade`` command (also ``python -m volshade``): ``volshade demo`` and
``volshade render VOLUME``.

    volshade demo [--out DIR] [--size N] [--image N] [--downsample F]
    volshade render VOLUME --out img.png [--preset NAME] [--azimuth A] [--elevation E] ...

VOLUME is a phantom name (shells, corner, orange, bucky, noise), a real-data
name (colin27, mni152, mni152_gm, mni152_wm: found via VOLSHADE_DATA) or a path to a
NIfTI file. The transfer function defaults to the volume's own preset (shells,
corner, head for colin27; grey otherwise), and the corner phantom's labels are
classified before interpolation. Lengths are in mm (a phantom's voxel is 1 mm),
converted to voxels of the smallest voxel edge for LAO and obscurances, which work in
voxels: on anisotropic data their reach is longer along the coarser axes.
Obscurances of real data are smoothed by one voxel and displayed with high 0.6 by
default: unsmoothed, the strict occlusion test on measured intensities draws the
voxel grid on the skin as striations, and surfaces come out dark.
"""

import argparse
import math
import pathlib
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass

import equinox as eqx
import jax
import numpy as np
from tqdm import tqdm

from . import data, transfer
from .camera import Camera
from .importance import Focus, Importance
from .lao import LocalAmbientOcclusion
from .obscurance import ObscuranceParams
from .render import save_png
from .scene import AMBIENT, Scene, render
from .shading import SHADERS


@dataclass
class Job:
    """One image of the demo: a name, a scene factory, a camera and the caption it gets
    in the side-by-side image."""

    name: str
    make_scene: Callable[[], Scene]
    camera: Camera
    caption: str


# volumes with a preset of their own (any other: "grey"), and label volumes, which are
# classified before interpolation (see volshade.render.march)
_PRESETS = {"shells": "shells", "corner": "corner", "colin27": "head"}
_LABELS = ("corner",)


def _is_measured(spec: str) -> bool:
    """Whether ``spec`` names real data (a dataset or a NIfTI path) and not a phantom."""
    if spec in data.PHANTOMS:
        return False
    if spec in data.DATASETS or pathlib.Path(spec).suffix in (".nii", ".gz"):
        return True
    valid = ", ".join([*data.PHANTOMS, *data.DATASETS])
    raise ValueError(f"unknown volume {spec!r}; use one of {valid} or a .nii/.nii.gz path.")


def _load_volume(spec: str, downsample: int | None, size: int | None, measured: bool):
    # an option that does not apply is refused, not ignored
    if measured:
        if size is not None:
            raise ValueError(f"--size sets a phantom's edge; {spec!r} is real data (use "
                             f"--downsample).")
        loader = data.load if spec in data.DATASETS else data.load_nifti
        return loader(spec, downsample=1 if downsample is None else downsample)
    if downsample is not None:
        raise ValueError(f"--downsample applies to real data; for the phantom {spec!r} "
                         f"use --size.")
    return data.phantom(spec, shape=96 if size is None else size), (1.0, 1.0, 1.0)


# ambient option -> (CLI options that only it reads, as argparse dests)
_AMBIENT_OPTIONS = {"lao": ("radius", "offset"),
                    "obscurance": ("d_max", "smoothing", "low", "high", "colour_bleeding")}


def _ambient_options(args: argparse.Namespace, measured: bool) -> dict:
    """The options of the ambient term, in mm, with their defaults (``smoothing`` None:
    one voxel edge), checked before the volume is loaded; the options of another ambient
    term are refused."""
    for ambient, names in _AMBIENT_OPTIONS.items():
        given = [f"--{n.replace('_', '-')}" for n in names
                 if getattr(args, n) is not None and getattr(args, n) is not False]
        if given and args.ambient != ambient:
            raise ValueError(f"{' and '.join(given)} {'is' if len(given) == 1 else 'are'} "
                             f"read only with --ambient {ambient}, got --ambient "
                             f"{args.ambient}.")
    if args.ambient == "lao":
        radius = 16.0 if args.radius is None else args.radius
        offset = 1.0 if args.offset is None else args.offset
        if not (math.isfinite(radius) and radius > offset >= 0):
            raise ValueError(f"--radius and --offset must be finite numbers with radius > "
                             f"offset >= 0 (mm), got {radius:g} and {offset:g}.")
        return {"radius": radius, "offset": offset}
    if args.ambient == "obscurance":
        d_max = 32.0 if args.d_max is None else args.d_max
        if not (math.isfinite(d_max) and d_max > 0):
            raise ValueError(f"--d-max must be a finite number > 0 (mm), got {d_max:g}.")
        if args.smoothing is not None and not (math.isfinite(args.smoothing)
                                               and args.smoothing >= 0):
            raise ValueError(f"--smoothing must be a finite number >= 0 (mm), got "
                             f"{args.smoothing:g}.")
        default_high = 0.6 if measured else 1.0
        low = 0.0 if args.low is None else args.low
        high = default_high if args.high is None else args.high
        for flag, value in (("--low", low), ("--high", high)):
            if not math.isfinite(value):
                raise ValueError(f"{flag} must be a finite number, got {value:g}.")
        if not low <= high:
            said = "" if args.high is not None else (
                f" (the default for {'real data' if measured else 'phantoms'})")
            raise ValueError(f"--low must be <= --high, got {low:g} and {high:g}{said}.")
        return {"d_max": d_max, "smoothing": args.smoothing, "low": low, "high": high,
                "color_bleeding": args.colour_bleeding}
    return {}


def _visible_radius(opacity: np.ndarray, spacing: tuple[float, float, float]) -> float:
    """The radius, in scene units (the volume's longest side is 1), of the sphere about
    the volume's centre that holds every voxel the transfer function shows (opacity
    above 0; where nothing shows, every voxel): the camera looks at the centre, so a
    view that holds the sphere holds them."""
    shape = np.asarray(opacity.shape)
    physical = shape * np.asarray(spacing)
    scale = float(physical.max())
    shown = np.argwhere(opacity > 0)
    if shown.size == 0:  # the box's corners
        return 0.5 * float(np.linalg.norm(physical)) / scale
    # voxel centres, and each voxel's half diagonal
    centres = ((shown + 0.5) / shape - 0.5) * physical / scale
    half_voxel = 0.5 * float(np.linalg.norm(np.asarray(spacing))) / scale
    return float(np.sqrt(np.max(np.sum(centres**2, axis=1)))) + half_voxel


def _fitting_camera(args: argparse.Namespace, opacity: np.ndarray,
                    spacing: tuple[float, float, float]) -> Camera:
    """The camera of the options: at ``--distance``, or (perspective, by default) the
    nearest at which the visible part of the volume fits the image (its field of view,
    30 degrees, holds the sphere of :func:`_visible_radius`, 2% spare); an orthographic
    view is as high as that sphere."""
    radius = 1.02 * _visible_radius(opacity, spacing)
    fov = 30.0
    if args.projection == "orthographic":
        return Camera.orbit(azimuth=args.azimuth, elevation=args.elevation,
                            image_shape=(args.image, args.image), projection="orthographic",
                            width=2 * radius)
    distance = (radius / math.sin(math.radians(fov / 2)) if args.distance is None
                else args.distance)
    return Camera.orbit(azimuth=args.azimuth, elevation=args.elevation, distance=distance,
                        image_shape=(args.image, args.image), fov=fov)


def _ambient_params(ambient: str, options: dict, voxel: float, smooth: bool) -> dict:
    """The Scene's ``lao`` or ``obscurance`` from :func:`_ambient_options`, lengths in
    voxels of the smallest edge ``voxel`` (mm); ``smooth``: the obscurance's smoothing
    defaults to one voxel edge (else 0)."""
    if ambient == "lao":
        return {"lao": LocalAmbientOcclusion(options["radius"] / voxel,
                                             offset=options["offset"] / voxel)}
    if ambient == "obscurance":
        smoothing = options["smoothing"]
        smoothing = (voxel if smooth else 0.0) if smoothing is None else smoothing
        return {"obscurance": ObscuranceParams(
            d_max=options["d_max"] / voxel, low=options["low"], high=options["high"],
            smoothing=smoothing / voxel, color_bleeding=options["color_bleeding"])}
    return {}


def _run_jobs(jobs: list[Job], out: pathlib.Path
              ) -> tuple[list[tuple[str, float]], dict[str, np.ndarray]]:
    out.mkdir(parents=True, exist_ok=True)
    timings = []
    rendered = {}
    for job in tqdm(jobs, desc="volshade demo", unit="image"):
        t0 = time.perf_counter()
        image = jax.block_until_ready(eqx.filter_jit(render)(job.make_scene(), job.camera))
        timings.append((job.name, time.perf_counter() - t0))
        rendered[job.name] = np.asarray(image)
        save_png(out / f"{job.name}.png", image)
    return timings, rendered


def _side_by_side(images: list[np.ndarray], captions: list[str],
                  background: tuple[float, float, float]) -> np.ndarray:
    """The images in a row, 4 white pixels apart, each over a band with its caption."""
    from PIL import Image, ImageDraw, ImageFont

    h, w = images[0].shape[:2]
    size = max(8, h // 14)
    while size > 8 and max(ImageFont.load_default(size=size).getlength(c)
                           for c in captions) > w - 4:
        size -= 1
    font = ImageFont.load_default(size=size)
    band = size + size // 2
    row = Image.new("RGB", (len(images) * (w + 4) - 4, band + h), (255, 255, 255))
    fill = tuple(round(255 * c) for c in background)
    draw = ImageDraw.Draw(row)
    for k, (img, caption) in enumerate(zip(images, captions, strict=True)):
        x = k * (w + 4)
        rgb = np.round(255 * np.clip(img[..., :3], 0, 1)).astype(np.uint8)
        row.paste(Image.fromarray(rgb), (x, band))
        draw.rectangle((x, 0, x + w - 1, band - 1), fill=fill)
        draw.text((x + w / 2, band / 2), caption, fill=(255, 255, 255), font=font,
                  anchor="mm")
    return np.asarray(row, np.float32) / 255


def demo(out: pathlib.Path, size: int, image: int, downsample: int) -> int:
    """Render the built-in phantom (and Colin27 when available) to PNGs in ``out``.

    Side by side and captioned (``<volume>_side_by_side.png``), for each volume:
    emission-absorption, Blinn-Phong, Blinn-Phong with local ambient occlusion; for the
    head also importance-aware composition revealing the skull through the skin inside a
    focus region.
    """
    shape = (image, image)
    bg = (0.08, 0.08, 0.1)
    vol = data.phantom("shells", shape=size)
    cut = vol.at[:, :, size // 2:].set(0)
    cam = Camera.orbit(azimuth=35, elevation=25, image_shape=shape)
    radius = size / 8
    shells_lao = LocalAmbientOcclusion(radius, offset=min(1.0, radius / 2), directions=16,
                                       samples=8)
    shells = dict(volume=cut, transfer=transfer.preset("shells"), background=bg)
    jobs = [
        Job("shells_none", lambda: Scene(**shells), cam, "no shading"),
        Job("shells_phong", lambda: Scene(**shells, shading="phong"), cam, "Phong"),
        Job("shells_lao", lambda: Scene(**shells, shading="phong", ambient="lao",
                                        lao=shells_lao), cam, "Phong + LAO"),
    ]
    try:
        head, spacing = data.load("colin27", downsample=downsample)
    except (FileNotFoundError, ImportError) as err:
        # the whole message: past its first line it says where it looked and how to get
        # the file
        print(f"volshade demo: skipping the Colin27 head:\n{err}")
    else:
        front = Camera.orbit(azimuth=30, elevation=10, image_shape=shape, distance=3.0)
        voxel = float(min(spacing))
        common = dict(volume=head, spacing=spacing, step=voxel / 2, background=bg)
        skin = dict(common, transfer=transfer.preset("head"))
        # LAO radius and offset are in voxels of the (downsampled) volume: ~12 mm and ~2 mm.
        head_lao = LocalAmbientOcclusion(12.0 / voxel, offset=2.0 / voxel, directions=16,
                                         samples=8)
        skull = Importance(intensity=-30.0, background=-1000.0)
        jobs += [
            Job("colin27_none", lambda: Scene(**skin), front, "no shading"),
            Job("colin27_phong", lambda: Scene(**skin, shading="phong"), front, "Phong"),
            Job("colin27_lao", lambda: Scene(**skin, shading="phong", ambient="lao",
                                             lao=head_lao), front, "Phong + LAO"),
            Job("colin27_importance", lambda: Scene(
                **common, transfer=transfer.preset("head_skull"), shading="phong",
                composition="importance", importance=skull,
                focus=Focus(center=(0.45, 0.5), radius=0.22, kind="circular")), front,
                "importance: skull"),
        ]
    t0 = time.perf_counter()
    timings, rendered = _run_jobs(jobs, out)
    for prefix in ("shells", "colin27"):
        panel = [job for job in jobs if job.name.startswith(prefix)]
        if len(panel) > 1:
            save_png(out / f"{prefix}_side_by_side.png", _side_by_side(
                [rendered[job.name] for job in panel], [job.caption for job in panel], bg))
    total = time.perf_counter() - t0
    parts = ", ".join(f"{name} {sec:.1f}s" for name, sec in timings)
    print(f"volshade demo: {len(jobs)} images in {total:.1f}s on {jax.devices()[0].platform} "
          f"({parts}) -> {out}/")
    return 0


def render_command(args: argparse.Namespace) -> int:
    # found before the render, not after it
    if args.out.is_dir() or args.out.suffix.lower() != ".png":
        raise ValueError(f"--out must name a .png file, got {str(args.out)!r}.")
    # (Scene refuses them too; here the message names the option) a PNG would clip them
    # silently; NaN is left to the render's own check
    if args.projection == "orthographic" and args.distance is not None:
        raise ValueError("--distance applies to perspective views: an orthographic view is "
                         "sized to hold what the transfer function shows; leave --distance "
                         "out.")
    if any(c < 0 or c > 1 for c in args.background):
        raise ValueError(f"--background must be three numbers in [0, 1] (R G B), got "
                         f"{' '.join(f'{c:g}' for c in args.background)}.")
    measured = _is_measured(args.volume)
    options = _ambient_options(args, measured)
    vol, spacing = _load_volume(args.volume, args.downsample, args.size, measured)
    voxel = float(min(spacing))
    # smoothed by default: measured data (its noise draws the voxel grid) and labels (a
    # wall of one label has no strictly denser neighbour to occlude it: obscurance 1)
    params = _ambient_params(args.ambient, options, voxel,
                             measured or args.volume in _LABELS)
    tf = transfer.preset(args.preset or _PRESETS.get(args.volume, "grey"))
    classification = args.classification or ("pre" if args.volume in _LABELS else "post")
    cam = _fitting_camera(args, np.asarray(tf.opacity(vol)), spacing)
    step = args.step if args.step is not None else voxel / 2
    scene = Scene(volume=vol, spacing=spacing, transfer=tf, shading=args.shading,
                  ambient=args.ambient, step=step, background=tuple(args.background),
                  classification=classification, **params)
    with tqdm(total=1, desc=f"rendering {args.volume}", unit="image") as bar:
        t0 = time.perf_counter()
        image = jax.block_until_ready(eqx.filter_jit(render)(scene, cam))
        bar.update()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_png(args.out, image)
    print(f"volshade render: {args.volume} {tuple(vol.shape)} -> {args.out} "
          f"in {time.perf_counter() - t0:.1f}s")
    return 0


class _Formatter(argparse.RawDescriptionHelpFormatter):
    """The module docstring as written, and each option's default (where it has one)
    after its help."""

    def _get_help_string(self, action):
        text = action.help or ""
        if action.option_strings and action.default not in (None, argparse.SUPPRESS):
            text += f"{' ' if text else ''}(default: %(default)s)"
        return text


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="volshade", description=__doc__,
                                     formatter_class=_Formatter)
    sub = parser.add_subparsers(dest="command", required=True)
    p_demo = sub.add_parser("demo", help="render built-in phantoms (and Colin27) to PNGs",
                            formatter_class=_Formatter)
    p_demo.add_argument("--out", type=pathlib.Path, default=pathlib.Path("volshade-demo"),
                        help="folder for the PNGs")
    p_demo.add_argument("--size", type=int, default=96, help="phantom edge in voxels")
    p_demo.add_argument("--image", type=int, default=256, help="image edge in pixels")
    p_demo.add_argument("--downsample", type=int, default=2,
                        help="integer block-mean factor for the real head")
    p_render = sub.add_parser("render", help="render one volume to a PNG",
                              formatter_class=_Formatter)
    p_render.add_argument("volume", help="phantom name, dataset name or NIfTI path")
    p_render.add_argument("--out", type=pathlib.Path, required=True, help="the PNG to write")
    p_render.add_argument("--preset", default=None,
                          help=f"one of {', '.join(transfer.PRESETS)} (default: the volume's "
                               f"own: shells, corner, head for colin27, grey otherwise)")
    p_render.add_argument("--classification", default=None, choices=["post", "pre"],
                          help="classify interpolated values (post) or interpolate classified "
                               "voxels (pre, for labels; default: pre for the corner phantom, "
                               "post otherwise)")
    p_render.add_argument("--shading", default="phong", choices=list(SHADERS),
                          help="local shading")
    # "volume" needs a volume and "feature_ao" its features: neither fits on a command line
    p_render.add_argument("--ambient", default="none",
                          choices=[a for a in AMBIENT if a not in ("volume", "feature_ao")],
                          help="ambient term")
    p_render.add_argument("--azimuth", type=float, default=30.0,
                          help="degrees about the d axis; 0 looks along -h (a head from the front)")
    p_render.add_argument("--elevation", type=float, default=20.0,
                          help="degrees; 90 looks down from +d")
    p_render.add_argument("--distance", type=float, default=None,
                          help="from the volume's centre; its longest side is 1 (default: "
                               "the nearest at which what the transfer function shows "
                               "fits the image; perspective only: an orthographic view "
                               "fits it)")
    p_render.add_argument("--projection", default="perspective",
                          choices=["perspective", "orthographic"], help="camera projection")
    p_render.add_argument("--image", type=int, default=256, help="image edge in pixels")
    p_render.add_argument("--size", type=int, default=None,
                          help="phantom edge in voxels (default: 96; phantoms only)")
    p_render.add_argument("--downsample", type=int, default=None,
                          help="integer block-mean factor (default: 1; real data only)")
    p_render.add_argument("--step", type=float, default=None,
                          help="sample distance in mm (default: half the smallest voxel edge)")
    p_render.add_argument("--background", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                          metavar=("R", "G", "B"), help="colour behind the volume, in [0, 1]")
    lao = p_render.add_argument_group("with --ambient lao")
    lao.add_argument("--radius", type=float, default=None,
                     help="LAO ray length R in mm (default: 16)")
    lao.add_argument("--offset", type=float, default=None,
                     help="LAO initial offset in mm, below the radius (default: 1)")
    obscurance = p_render.add_argument_group("with --ambient obscurance")
    obscurance.add_argument("--d-max", type=float, default=None,
                            help="largest occluder distance in mm (default: 32)")
    obscurance.add_argument("--smoothing", type=float, default=None,
                            help="Gaussian sigma in mm on the density before the occluder "
                                 "search (default: one voxel edge for real data and the "
                                 "corner phantom's labels, 0 for the other phantoms)")
    obscurance.add_argument("--low", type=float, default=None,
                            help="display threshold: obscurance below it is 0 (default: 0)")
    obscurance.add_argument("--high", type=float, default=None,
                            help="display threshold: obscurance above it is 1 (default: 0.6 "
                                 "for real data, 1 for phantoms)")
    obscurance.add_argument("--colour-bleeding", action="store_true",
                            help="tint by the occluders' colours")
    parser.set_defaults(_commands={"demo": p_demo, "render": p_render})
    return parser


def _check_message(err: Exception) -> str:
    """The message of a failed run-time check, without equinox's stack and advice."""
    marker = "EquinoxRuntimeError: "
    for line in str(err).splitlines():
        if marker in line:
            return line.split(marker, 1)[1]
    return str(err)


def main(argv: list[str] | None = None) -> int:
    args, unknown = _parser().parse_known_args(argv)
    # errors carry the command's name ("volshade render: error: ..."), as argparse's do
    command = args._commands[args.command]
    if unknown:  # with the command's usage, not the top-level one's
        command.error(f"unrecognized arguments: {' '.join(unknown)}")
    prefix = f"{command.prog}: error:"
    try:
        for name in ("size", "image", "downsample"):
            if getattr(args, name, 1) is not None and getattr(args, name, 1) < 1:
                raise ValueError(f"--{name} must be >= 1, got {getattr(args, name)}.")
        if args.command == "demo":
            return demo(args.out, args.size, args.image, args.downsample)
        return render_command(args)
    except (ValueError, TypeError, OSError, ImportError) as err:
        print(f"{prefix} {err}", file=sys.stderr)
        return 2
    except eqx.EquinoxRuntimeError as err:  # a run-time check (e.g. NaN in a parameter)
        print(f"{prefix} {_check_message(err)}", file=sys.stderr)
        return 2
    except OverflowError:  # a size past what an index can hold (--image 3000000000)
        print(f"{prefix} a size is too large to index (past 2^31); lower --size or "
              "--image, or raise --downsample.", file=sys.stderr)
        return 2
    except (MemoryError, jax.errors.JaxRuntimeError) as err:
        # NumPy's or XLA's allocation; other run-time errors are bugs, with a traceback
        if not isinstance(err, MemoryError) and "RESOURCE_EXHAUSTED" not in str(err):
            raise
        print(f"{prefix} out of memory; lower --size or --image, or raise "
              "--downsample (or a render's --step).", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
