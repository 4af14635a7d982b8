"""What the LAO Pallas kernels compile to on an H100/H200, without one: registers,
spills and instructions per voxel and sample, from Triton's own compiler.

    python -m benchmarks.run pallas_sass

Lowers ``lao(..., implementation="pallas")`` (value and gradient, issue 3's case:
512^3, L = 54, M = 50, R = 50) for CUDA on this machine, compiles each kernel's
Triton IR with the ``triton`` package for sm_90a, and reads ``ptxas -v`` and the SASS
(``cuobjdump``; both ship in Triton's wheel). For every launch in
``volshade._lao_pallas.LAUNCHES`` (and without ``--quick`` the reverse-mode
``GRADIENT_LAUNCHES`` and ``CORRECTED_GRADIENT_LAUNCHES``), with and without opacity
correction:

* registers and spill bytes of each kernel, and the warps of it that fit on a
  multiprocessor by registers (65536 per multiprocessor, allocated per warp in
  multiples of 256, at most 64 warps: Hopper's published limits);
* instructions per voxel and sample: the sample loop of the forward and chunk-start
  kernels, and the whole cotangent and adjoint kernels over a chunk, divided by the
  voxels a thread owns (and the chunk's samples);
* the load instructions by width (``LDG.E.128`` loads four voxels).

A static measure, not a timing: it shows where instructions go. For scale (from the
published peaks, not measured): an H100 SXM issues 4 x 32 thread instructions per
multiprocessor and clock (132 of them at 1.98 GHz), so the forward's 30
instructions a sample bound it near 1.1 T samples/s, and its L1 delivers 128 bytes per
multiprocessor and clock while a sample reads 32 (eight corners of four bytes),
about 1.05 T/s: both limits sit near issue 3's goal of 1 T/s. Needs ``pip install
triton`` and a jaxlib that embeds Triton IR in its custom call (0.10.2 here; later
ones compile while lowering, on a GPU).
"""

import collections
import contextlib
import io
import math
import pathlib
import re
import subprocess
import tempfile

import jax
import jax.numpy as jnp
from jax import export

import volshade.directions as vdirs

_KERNELS = ("_forward_kernel", "_chunk_starts_kernel", "_chunk_cotangents_kernel",
            "_chunk_adjoint_kernel")


def _triton_modules(launch, correction: bool, n: int, n_dirs: int, samples: int,
                    radius: float) -> dict[str, str]:
    """Each kernel's Triton IR as text, as Pallas prints it with ``debug=True``."""
    from jax.experimental import pallas as pl

    from volshade import _lao_pallas as pallas

    dirs = vdirs.fibonacci(n_dirs).astype(jnp.float32)
    pad = (math.ceil(radius) + 1,) * 3

    def value_and_grad(alpha, r):
        def total(a, r):
            return jnp.sum(pallas.occlusion_sum(
                a, dirs, jnp.full((n_dirs,), 1 / n_dirs, jnp.float32), r, 1.0, pad=pad,
                samples=samples, correction=correction, launch=launch))
        return jax.value_and_grad(total, argnums=(0, 1))(alpha, r)

    original = pl.pallas_call
    printed = io.StringIO()
    try:
        pallas.pl.pallas_call = lambda *a, **k: original(*a, **{**k, "debug": True})
        with contextlib.redirect_stdout(printed):
            export.export(jax.jit(value_and_grad), platforms=["cuda"], disabled_checks=[
                export.DisabledSafetyCheck.custom_call("__gpu$xla.gpu.triton")])(
                jax.ShapeDtypeStruct((n, n, n), jnp.float32),
                jax.ShapeDtypeStruct((), jnp.float32))
    finally:
        pallas.pl.pallas_call = original
    modules = {}
    for part in printed.getvalue().split("The Triton module for pallas_call")[1:]:
        text = re.sub(r" \[unknown\]", "", part)
        start = text.index("module @")
        text = text[start:text.index("\n}\n", start) + 3]
        # drop the debug locations, which Triton's parser does not read back
        text = re.sub(r' "[^"\n]*"\((?:#loc\d*|\[unknown\])\)', "", text)
        text = re.sub(r" \(?#loc\d*\)?", "", text)
        modules[re.search(r"tt.func public @(\w+)", text).group(1)] = text
    return modules


def _ptxas(bin_dir: pathlib.Path) -> pathlib.Path:
    """The ``ptxas`` Triton itself compiles sm_90a with (``get_ptxas``): Triton 3.9 ships
    a second, newer one for sm_90 and up, whose PTX (ISA 9.4) the first rejects; 3.6
    answers its only one; older wheels have no ``get_ptxas``."""
    try:
        from triton.backends.nvidia.compiler import get_ptxas
    except ImportError:
        return bin_dir / "ptxas"
    return pathlib.Path(get_ptxas(90).path)


def _sass(ttir: str, num_warps: int, work: pathlib.Path, name: str) -> dict:
    """Compile for sm_90a; registers, spills and the SASS instructions."""
    import triton
    from triton.backends.compiler import GPUTarget

    bin_dir = pathlib.Path(triton.__file__).parent / "backends" / "nvidia" / "bin"
    source = work / f"{name}.ttir"
    source.write_text(ttir)
    compiled = triton.compile(str(source), target=GPUTarget("cuda", 90, 32),
                              options={"num_warps": num_warps, "num_stages": 1})
    ptx = work / f"{name}.ptx"
    ptx.write_text(compiled.asm["ptx"])
    cubin = work / f"{name}.cubin"
    info = subprocess.run([_ptxas(bin_dir), "-arch=sm_90a", "-v", ptx, "-o", cubin],
                          capture_output=True, text=True, check=True).stderr
    sass = subprocess.run([bin_dir / "cuobjdump", "--dump-sass", cubin], capture_output=True,
                          text=True, check=True).stdout
    instructions, labels = _parse_sass(sass)
    return {"registers": int(re.search(r"Used (\d+) registers", info).group(1)),
            "spill_bytes": int(re.search(r"(\d+) bytes spill stores", info).group(1)),
            "instructions": instructions, "labels": labels}


def _resident_warps(registers: int, num_warps: int) -> int:
    """Warps of a kernel that fit on one Hopper multiprocessor by their registers."""
    per_warp = -(-registers // 8) * 8 * 32
    return num_warps * min(64 // num_warps, 65536 // (per_warp * num_warps))


def _parse_sass(sass: str) -> tuple[list[tuple[int, str]], dict[str, int]]:
    """``cuobjdump --dump-sass`` text -> ``[(address, instruction)]`` and the address of
    each branch label (``.L_x_N:`` lines name the instruction after them)."""
    instructions, labels, pending = [], {}, []
    for line in sass.splitlines():
        label = re.match(r"\s*\.(L_x_\d+):", line)
        if label:
            pending.append(label.group(1))
            continue
        match = re.match(r"\s*/\*([0-9a-f]{4,})\*/\s+(.*?)\s*;", line)
        if match:
            address = int(match.group(1), 16)
            labels.update(dict.fromkeys(pending, address))
            pending = []
            instructions.append((address, match.group(2)))
    return instructions, labels


def _innermost_loop(instructions, labels) -> list[str]:
    """The body of the shortest backward branch (the sample loop); its target is a label
    (``BRA `(.L_x_N)``) or an address (``BRA 0x...``)."""
    loops = []
    for address, text in instructions:
        match = re.search(r"BRA (?:`\(\.(L_x_\d+)\)|0x([0-9a-f]+))", text)
        if not match:
            continue
        target = labels.get(match.group(1)) if match.group(1) else int(match.group(2), 16)
        if target is not None and target < address:
            loops.append((target, address))
    if not loops:
        raise RuntimeError("benchmarks.pallas_sass: no backward branch in the kernel's SASS, "
                           "so its sample loop cannot be told apart; read the SASS by hand.")
    low, high = min(loops, key=lambda loop: loop[1] - loop[0])
    return [text for address, text in instructions if low <= address <= high]


def run(quick: bool, *, n: int = 512, n_dirs: int = 54, samples: int = 50,
        radius: float = 50.0) -> dict:
    try:
        import triton  # noqa: F401
    except ImportError as err:
        raise SystemExit("benchmarks.run pallas_sass needs Triton's compiler: "
                         "`pip install triton`.") from err
    from jax._src.lib import version

    if version > (0, 10, 2):
        raise SystemExit("benchmarks.run pallas_sass reads the Triton IR that jaxlib <= "
                         "0.10.2 embeds; later jaxlibs compile it while lowering, on a GPU.")
    from volshade import _lao_pallas as pallas
    from volshade.lao import _chunking

    launches = pallas.LAUNCHES[:2] if quick else dict.fromkeys(
        pallas.LAUNCHES + pallas.GRADIENT_LAUNCHES + pallas.CORRECTED_GRADIENT_LAUNCHES)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = pathlib.Path(tmp)
        for launch in launches:
            _, chunk = _chunking(samples - 1, launch.chunk)
            for correction in (False, True):
                modules = _triton_modules(launch, correction, n, n_dirs, samples, radius)
                cotangent_tile = (launch.corrected_cotangent_tile if correction
                                  else launch.cotangent_tile)
                for kernel in _KERNELS:
                    compiled = _sass(modules[kernel], launch.num_warps, work, kernel)
                    tile = cotangent_tile if kernel == "_chunk_cotangents_kernel" else launch.tile
                    per_thread = math.prod(tile) / (32 * launch.num_warps)
                    if kernel in ("_forward_kernel", "_chunk_starts_kernel"):
                        body = _innermost_loop(compiled["instructions"], compiled["labels"])
                        samples_per_body = 1
                    else:
                        body = [text for _, text in compiled["instructions"]]
                        samples_per_body = chunk
                    loads = collections.Counter(
                        re.search(r"LDG\S*", t).group(0) for t in body if "LDG" in t)
                    rows.append({
                        "case": f"{kernel} tile {tile} warps {launch.num_warps} vector "
                                f"{launch.vector} chunk {chunk} correction {correction}",
                        "registers": compiled["registers"],
                        "spill_bytes": compiled["spill_bytes"],
                        "resident_warps": _resident_warps(compiled["registers"],
                                                          launch.num_warps),
                        "instructions_per_voxel_sample":
                            len(body) / (per_thread * samples_per_body),
                        "loads": " ".join(f"{k}:{v}" for k, v in sorted(loads.items())),
                    })
    return {"title": "LAO Pallas kernels compiled for sm_90a (static)",
            "sizes": {"n": n, "directions": n_dirs, "samples": samples, "radius": radius,
                      "quick": quick},
            "rows": rows, "ratios": {}}
