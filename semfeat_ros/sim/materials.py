"""Material ids and class ids used by the world builder and the shader."""
from __future__ import annotations

from semfeat_ros.labels import load_labels

_L = load_labels()
ROAD = _L.id_of('road')
SIDEWALK = _L.id_of('sidewalk')
PARKING_LINE = _L.id_of('parking_line')
LANE_DIVIDER = _L.id_of('lane_divider')
ROAD_MARKING = _L.id_of('road_marking')
CURB = _L.id_of('curb')
WALL = _L.id_of('wall')
PILLAR = _L.id_of('pillar')
CEILING = _L.id_of('ceiling')
LIGHT = _L.id_of('light')
SIGN = _L.id_of('sign')
POLE = _L.id_of('pole')
RAILING = _L.id_of('railing')
BARRIER = _L.id_of('barrier')
BUILDING = _L.id_of('building')
VEGETATION = _L.id_of('vegetation')
SKY = _L.id_of('sky')
CAR = _L.id_of('car')
PEDESTRIAN = _L.id_of('pedestrian')
NUM_CLASSES = len(_L)
IGNORE = 255
"""Label of pixels outside the lens's image circle (no ray)."""

# Materials (shader programs). The shader dispatches on these ids.
M_FLOOR_IN = 0  # covered-level floor: concrete with oil stains, tyre marks
M_FLOOR_DECK = 1  # deck coating
M_CONCRETE = 2  # walls, beams, stair cores
M_PILLAR = 3  # concrete pillar with a painted band
M_CEILING = 4  # slab underside
M_METAL = 5  # railings, poles, lamp housings
M_SIGN = 6  # sign face with lettering (param: sign design)
M_CAR = 7  # car body paint (+ lights, plate on front/back faces)
M_GLASS = 8  # car windows
M_RUBBER = 9  # tyres
M_FACADE = 10  # building facade with windows
M_FOLIAGE = 11  # tree crowns, hedges
M_BARK = 12  # tree trunks
M_ASPHALT = 13  # streets
M_PAVER = 14  # sidewalks
M_LAMP = 15  # emissive light fixture
M_STRIPES = 16  # red/white or orange/white barrier stripes
M_CLOTH = 17  # pedestrian clothing
M_SKIN = 18  # pedestrian head
M_CURB = 19  # curbs, wheel stops
M_RAMP = 20  # ramp surface (grooved concrete)
N_MATERIALS = 21
