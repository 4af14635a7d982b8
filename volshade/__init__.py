"""volshade: differentiable volume shading for direct volume rendering, in JAX.

The public API. Submodules hold the details (``volshade.data``, ``volshade.transfer``,
``volshade.directions``, ``volshade.gradient``, ``volshade.sampling``); the kernels
and parameter modules are re-exported here. Where a function has its module's name
(``volshade.lao``, ``volshade.render``, ``volshade.fit``, ``volshade.obscurance``, ...)
the attribute is the function; import the module's other names from it, e.g.
``from volshade.render import march``.
"""

from . import data as data
from . import directions as directions
from . import gradient as gradient
from . import sampling as sampling
from . import transfer as transfer
from .camera import Camera as Camera
from .cao import contextual_ao as contextual_ao
from .clip import BoxClip as BoxClip
from .clip import HalfSpaceClip as HalfSpaceClip
from .clip import SphereClip as SphereClip
from .clip import TorusClip as TorusClip
from .clip import affected_mask as affected_mask
from .clip import clip_mask as clip_mask
from .clip import clip_opacity as clip_opacity
from .composition import composite as composite
from .feature_ao import FeatureAmbientOcclusion as FeatureAmbientOcclusion
from .feature_ao import feature_ao as feature_ao
from .feature_ao import merge_feature_ao as merge_feature_ao
from .fit import Fit as Fit
from .fit import GaussNewtonLineSearch as GaussNewtonLineSearch
from .fit import fit as fit
from .gradient import regression_gradient as regression_gradient
from .importance import Focus as Focus
from .importance import Importance as Importance
from .importance import focus_weights as focus_weights
from .importance import sample_importance as sample_importance
from .lao import LocalAmbientOcclusion as LocalAmbientOcclusion
from .lao import lao as lao
from .obscurance import ObscuranceParams as ObscuranceParams
from .obscurance import obscurance as obscurance
from .obscurance import obscurance_shading as obscurance_shading
from .obscurance import occluder_distances as occluder_distances
from .obscurance import threshold as threshold
from .render import save_png as save_png
from .saliency import SaliencyModulation as SaliencyModulation
from .saliency import least_salient_view as least_salient_view
from .saliency import modulate_opacity as modulate_opacity
from .saliency import most_salient_view as most_salient_view
from .saliency import projected_area as projected_area
from .saliency import saliency as saliency
from .saliency import viewpoint_saliency as viewpoint_saliency
from .scene import Scene as Scene
from .scene import render as render
from .shading import Phong as Phong
from .transfer import IntervalFeature as IntervalFeature
from .transfer import TransferFunction as TransferFunction

__version__ = "0.1.0"
