"""soft_rom: linear reduced-order models of soft robots from ROS 2 bags.

Lagrangian Operator Inference (LOpInf), DMD with control and ERA/OKID, after Sharma et al.,
*Data-driven Model Reduction for Soft Robots via Lagrangian Operator Inference*.

The core (everything outside :mod:`soft_rom.ros`) never imports ROS.
"""

from __future__ import annotations

__version__ = '0.1.0'

from soft_rom.data import Episode  # noqa: E402
from soft_rom.models import DiscreteModel, LinearROM, load_model, SecondOrderModel  # noqa: E402

__all__ = ['DiscreteModel', 'Episode', 'LinearROM', 'SecondOrderModel', 'load_model',
           '__version__']
