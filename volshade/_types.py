"""One vocabulary of array dimension names for jaxtyping annotations.

Axis order everywhere is ``(D, H, W)`` (array order of a volume, slowest first);
points and directions in volume space are given in the same order, ``(d, h, w)``.
``"n 3"`` are points or directions, ``"S"`` samples along a ray, ``"L 3"`` a set
of ray directions, ``"*batch"`` leading batch axes (pixels, rays).
"""

from jaxtyping import Array, ArrayLike, Bool, Float, Int, Real

Volume = Float[Array, "D H W"]
RGBVolume = Float[Array, "D H W 3"]
Points = Float[Array, "n 3"]
Directions = Float[Array, "L 3"]
Scalar = Float[ArrayLike, ""]

__all__ = ["Array", "ArrayLike", "Bool", "Float", "Int", "Real", "Volume", "RGBVolume",
           "Points", "Directions", "Scalar"]
