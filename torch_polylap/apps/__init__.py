"""Applications of the polygon Laplacian (AW11 sec. 5): flows, plates, parameterizations.

``__all__`` is the modules' own ``__all__`` lists (flow, plate, conformal, planarize), so that
a name is made public in one place.
"""

from . import conformal, flow, plate
from . import planarize as _planarize  # the module: its function takes the name below
from .conformal import *
from .flow import *
from .planarize import *
from .plate import *

__all__ = [*flow.__all__, *plate.__all__, *conformal.__all__, *_planarize.__all__]
