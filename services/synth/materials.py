"""Material and ground-zone ids and the layout of the per-primitive parameter rows.

Shared by the scene generator (plain Python) and the numba kernels (read as compile-time constants).
Colours are linear-light albedos in [0, 1].
"""

from __future__ import annotations

# box materials
MAT_BUILDING = 0  # facades (window grid, shop fronts, brick/plaster/panels or photo) and a flat roof
MAT_ROOFBOX = 1  # rooftop structures: HVAC units, stair houses
MAT_CAR = 2  # car body (P_STYLE = 0) or cabin (P_STYLE = 1)
MAT_KIOSK = 3
MAT_KERB = 4
MAT_TRUNK = 5
MAT_POLE = 6  # street lamp pole and head
# sphere materials
MAT_CROWN = 10  # tree crown
MAT_BUSH = 11

BOX_MATERIALS = {
    MAT_BUILDING: "building",
    MAT_ROOFBOX: "roofbox",
    MAT_CAR: "car",
    MAT_KIOSK: "kiosk",
    MAT_KERB: "kerb",
    MAT_TRUNK: "trunk",
    MAT_POLE: "pole",
}
SPHERE_MATERIALS = {MAT_CROWN: "crown", MAT_BUSH: "bush"}

# ground zones (raster `zone`, one uint8 per cell)
Z_FIELD = 0  # outside the city: meadow
Z_ROAD = 1  # asphalt with lane markings, zebra crossings, manholes, drains
Z_SIDEWALK = 2  # paving tiles
Z_GRASS = 3
Z_PARKING = 4
Z_PAVED = 5  # cobblestones (yards between buildings)
Z_UNDER = 6  # under a building (never seen)
ZONES = {
    Z_FIELD: "field",
    Z_ROAD: "road",
    Z_SIDEWALK: "sidewalk",
    Z_GRASS: "grass",
    Z_PARKING: "parking",
    Z_PAVED: "paved",
    Z_UNDER: "under",
}

# parameter row of a primitive (float64, NPAR values)
P_R, P_G, P_B = 0, 1, 2  # main colour (facade, roof box, car paint, kiosk, crown)
P_STYLE = 3  # facade: 0 plaster, 1 brick, 2 concrete panels; roof box: 0 metal, 1 stair house; car: part
P_FLOOR = 4  # floor height (m)
P_GFLOOR = 5  # ground-floor height (m), 0 for an upper (setback) box
P_BAY = 6  # window bay width (m)
P_WINW = 7  # window width / bay width
P_WINH = 8  # window height / floor height
P_SHOP = 9  # probability that a ground-floor bay is a shop front
P_ROOF = 10  # roof type: 0 gravel, 1 membrane, 2 green, 3 metal sheet
P_R2, P_G2, P_B2 = 11, 12, 13  # secondary colour (roof of a building; glass tint of a car cabin)
P_SEED = 14  # integer seed of the primitive's texture
P_PHOTO = 15  # photo texture: width (m) of one photo on the facade, or -1 for procedural facades
P_Z0 = 16  # base height of the floor grid (m)
P_PARAPET = 17  # parapet height above the top floor (m)
P_AXIS = 18  # long axis of a car: 0 = x, 1 = y
P_FR, P_FG, P_FB = 19, 20, 21  # window frame colour
P_DOOR = 22  # door position on a facade, in [0, 1)
P_RELIEF = 23  # facade: depth (m) of the openings' reveals (windows, doors, shop windows); 0: flat
P_WALL = 24  # facade: the wall photo (services.synth.walls crop index) tiled over it, or -1
P_WALL_M = 25  # facade: metres per pixel of that wall photo
NPAR = 26

# lighting row (float64)
L_SUN = 0  # 3: unit vector towards the sun (ENU)
L_SUNC = 3  # 3: sun irradiance (linear RGB)
L_AMB = 6  # 3: sky (ambient) irradiance
L_ZEN = 9  # 3: sky radiance at the zenith
L_HOR = 12  # 3: sky radiance at the horizon
L_HAZEC = 15  # 3: haze colour
L_HAZED = 18  # haze distance (m): weight of the haze is 1 - exp(-distance / L_HAZED)
L_SHADOW = 19  # 1: cast shadow rays
L_CLOUD = 20  # cloud cover in [0, 1]
NLIGHT = 24
