"""ROS 2 bags: the only part of soft_rom that imports rosbags.

- :class:`EpisodeBagWriter` / :class:`BagTopics`: write episodes as bags (sqlite3 or MCAP)
  laid out as a SOFA + ROS 2 recording (the bag contract, ``docs/bag_contract.md``).
- :mod:`soft_rom.bags.reader`: open bags, describe them (``soft-rom info``) and stream
  decoded messages as numpy arrays for the converter (:mod:`soft_rom.convert`).
- :mod:`soft_rom.bags.replay_io`: ``soft-rom replay``, the predictor node's loop run offline
  over an episode or a bag, its topics written by
  :class:`~soft_rom.bags.prediction_writer.PredictionBagWriter`.
"""

from __future__ import annotations

from soft_rom.bags.reader import BagMessage, BagReader, describe_bag, is_bag
from soft_rom.bags.writer import BagTopics, EpisodeBagWriter, STORAGES

__all__ = ['BagMessage', 'BagReader', 'BagTopics', 'EpisodeBagWriter', 'STORAGES',
           'describe_bag', 'is_bag']
