"""volshade: differentiable volume shading for direct volume rendering, in JAX."""

from . import data as data
from . import directions as directions
from . import gradient as gradient
from . import sampling as sampling
from . import transfer as transfer
from .camera import Camera as Camera
from .composition import composite as composite
from .gradient import regression_gradient as regression_gradient
from .render import save_png as save_png
from .scene import Scene as Scene
from .scene import render as render
from .shading import Phong as Phong
from .transfer import IntervalFeature as IntervalFeature
from .transfer import TransferFunction as TransferFunction

__version__ = "0.1.0"
