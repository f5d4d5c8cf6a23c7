"""ROS-free real-time predictor: a loaded ROM, its state, held inputs, envelopes, a monitor.

This is everything the predictor node (:mod:`soft_rom.ros.predictor_node`) does, without
ROS: the node converts messages (:mod:`soft_rom.predictor.conversions`), hands them to a
:class:`~soft_rom.predictor.loop.RuntimeLoop` around a :class:`Predictor` and publishes
what the loop says is due; ``soft-rom replay`` (and ``--stream``) run the same loop offline.

Modules: :mod:`~soft_rom.predictor.config` (settings, health levels),
:mod:`~soft_rom.predictor.core` (inputs, time, health; with
:mod:`~soft_rom.predictor.stepping` and :mod:`~soft_rom.predictor.measuring`),
:mod:`~soft_rom.predictor.dynamics` (linear fast path, model protocol, Kalman gain),
:mod:`~soft_rom.predictor.envelope` (training envelope, bounds),
:mod:`~soft_rom.predictor.monitor` (windowed error), :mod:`~soft_rom.predictor.health`,
:mod:`~soft_rom.predictor.loop` (publish schedule, rates, diagnostics;
:mod:`~soft_rom.predictor.seqclock` stamps un-stamped messages),
:mod:`~soft_rom.predictor.params` (node parameters), :mod:`~soft_rom.predictor.replay`.
"""

from soft_rom.predictor.config import Health, Level, PredictorConfig
from soft_rom.predictor.core import Predictor
from soft_rom.predictor.dynamics import kalman_gain, model_info
from soft_rom.predictor.envelope import training_envelope
from soft_rom.predictor.replay import kalman_vs_open_loop, replay_episode, ReplayResult

__all__ = [
    'Health',
    'Level',
    'Predictor',
    'PredictorConfig',
    'ReplayResult',
    'kalman_gain',
    'kalman_vs_open_loop',
    'model_info',
    'replay_episode',
    'training_envelope',
]
