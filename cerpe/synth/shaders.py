"""Which shader draws each material kind of :mod:`cerpe.synth.textures` (the renderer's lookup)."""
from __future__ import annotations

from .materials_indoor import (shade_books, shade_cardboard, shade_ceiling, shade_floor, shade_plain, shade_robot,
                               shade_wall, shade_wood)
from .materials_outdoor import shade_car, shade_facade, shade_ground, shade_poster, shade_roof

# indexed by the material kinds (textures.GROUND ... textures.PLAIN)
SHADERS = (shade_ground, shade_facade, shade_roof, shade_car, shade_poster, shade_wall, shade_floor,
           shade_ceiling, shade_wood, shade_books, shade_cardboard, shade_robot, shade_plain)
