"""The contract both sides share: NumPy and the standard library only, imports nothing else.

The JAX simulation (`jaxmripp.sim`) and the onboard runtime (`jaxmripp.runtime`) both
build on these definitions, so a code, a heading, a feature column or the message format
is written once:

- `grid`: occupancy codes, headings, voxel indexing and the traversal of a line of flight;
- `flight`: safe flight -- known-free space, closest approach, intents, collisions;
- `vectors`: 3-vector arithmetic that NumPy and JAX evaluate to the same bits;
- `layout`: the policy's input columns (per candidate and per robot);
- `feeding`: which poses enter a robot's GPs, in which order, and how many per round;
- `sharing`: what robots in range learn of each other's maps;
- `view`: the view-gain features' model of the sensor and the facades;
- `belief`: where the windows not found yet are likely to be (the target belief);
- `sectors`: a division of the world among the team that needs no radio;
- `protocol`: the radio message formats and their version.
"""

from jaxmripp.spec.grid import (FREE, HEADING_ANGLES, HEADING_NAMES, HEADING_VECTORS,
                                N_HEADINGS, OCCUPIED, UNKNOWN, traversal_steps)
from jaxmripp.spec.layout import FEATURES, N_GLOBAL_EXTRA, ROBOT_STATE
from jaxmripp.spec.protocol import MAP_MESSAGE_TYPE, MAX_BYTES, MESSAGE_TYPE, PROTOCOL_VERSION

__all__ = [
    "FEATURES", "FREE", "HEADING_ANGLES", "HEADING_NAMES", "HEADING_VECTORS",
    "MAP_MESSAGE_TYPE", "MAX_BYTES", "MESSAGE_TYPE", "N_GLOBAL_EXTRA", "N_HEADINGS", "OCCUPIED", "PROTOCOL_VERSION",
    "ROBOT_STATE", "UNKNOWN", "traversal_steps",
]
