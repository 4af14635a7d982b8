"""volshade: differentiable volume shading for direct volume rendering, in JAX."""

from . import directions as directions
from . import gradient as gradient
from . import sampling as sampling
from .composition import composite as composite
from .gradient import regression_gradient as regression_gradient

__version__ = "0.1.0"
