"""The learning-curve study (``soft-rom study --learning-curve``).

How much training data a nonlinear ROM needs before it beats a linear one, and whether it
hurts where the robot is nearly linear: :mod:`~soft_rom.study.curve.core` (held-out choices,
test scores), :mod:`~soft_rom.study.curve.run` (data and the run), and
:mod:`~soft_rom.study.curve.report` (figure and Markdown).
"""

from soft_rom.study.curve.core import CurveConfig, CurveData, learning_curve, score
from soft_rom.study.curve.run import run_learning_curve

__all__ = ['CurveConfig', 'CurveData', 'learning_curve', 'run_learning_curve', 'score']
