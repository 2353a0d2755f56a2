"""The scene's light: the sun's position for a time, date and place, and the colours the renderer lights with.

* :func:`solar_position`: NOAA's solar calculator (Meeus' low-precision formulas, with NOAA's
  refraction), good to about 0.01 deg of elevation between 1800 and 2100 for suns well above the
  horizon, far better than the shadows need.
* :func:`resolve_lighting` turns a :class:`~droneulator.config.LightConfig`, a scene and a home position
  into a :class:`Lighting`: the direction towards the sun (Z-up ENU world: x east, y north), the direct
  sun's colour, the hemisphere ambient, the sky gradient and the haze. With every light field null it
  is exactly the renderer's historical light (the scene's fixed sun, today's constants).

The model (docs/light.md): the direct sun reddens and dims with the air mass it crosses (Kasten and
Young's air mass, a Rayleigh-like optical depth per channel) and sets between -1 and +1 deg elevation;
skylight and sky fade with elevation through civil twilight to a dim night floor (no moon). Cloud
cover ``c`` scales the direct sun by ``1 - c`` and blends ambient and sky towards an overcast grey.
Haze (Koschmieder): ``colour = c exp(-beta d) + fog (1 - exp(-beta d))``, ``beta = 3.912 / V`` for a
meteorological visibility ``V``; the haze lies in a layer :data:`HAZE_LAYER_M` deep, which also dims the
direct sun along its slant path through the layer, the lost light going to the diffuse part as clouds'.
Colours are the renderer's own units: multipliers of the texture albedo, 1.0 full scale.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
from dataclasses import dataclass

import numpy as np

from droneulator.config.light import DEFAULT_DATE, LightConfig
from droneulator.config.site import SiteConfig
from droneulator.scenes.base import Scene

#: the renderer's historical light (before the light section): direct sun, and the hemisphere ambient
#: of surfaces facing down and up
SUN_COLOR = (0.78, 0.74, 0.66)
AMBIENT_GROUND = (0.30, 0.28, 0.24)
AMBIENT_SKY = (0.50, 0.55, 0.62)
#: the sky's horizon is its zenith colour this far towards white
HORIZON_WHITENING = 0.45
#: the default scene sun's elevation (``Scene.sun_direction`` = (0.4, 0.3, 0.85)): a computed sun this
#: high has exactly the historical colours, lower ones redder and dimmer, higher ones a little brighter
REFERENCE_ELEVATION_DEG = math.degrees(math.asin(0.85 / math.sqrt(0.4**2 + 0.3**2 + 0.85**2)))
#: optical depth per unit air mass of the R, G, B channels on top of what the reference sun already
#: crosses (Rayleigh-like: blue scatters most), so the sun at 10 deg is about (0.77, 0.64, 0.43) of the
#: reference and at 3 deg orange
SUN_OPTICAL_DEPTH = (0.06, 0.10, 0.19)
#: below this elevation (deg) the sun is gone; it rises through [-1, +1] deg (its disc and refraction)
SUNSET_DEG = (-1.0, 1.0)
#: skylight at night, as a fraction of the reference's (a dim floor: the renderer has no moon or stars)
NIGHT_SKYLIGHT = 0.04
#: civil twilight: skylight fades from the horizon down to this elevation (deg)
TWILIGHT_DEG = -6.0
#: overcast ambient (facing down, facing up) and sky (zenith, horizon) at the reference elevation
OVERCAST_AMBIENT_GROUND = (0.40, 0.40, 0.40)
OVERCAST_AMBIENT_SKY = (0.80, 0.81, 0.83)
OVERCAST_ZENITH = (0.60, 0.62, 0.65)
OVERCAST_HORIZON = (0.80, 0.81, 0.83)
#: the haze's own colour in clear weather (bright grey-blue), before the skylight scales it
HAZE_COLOR = (0.78, 0.80, 0.84)
#: depth of the haze layer over the ground, metres: the sky's haze and the sun's slant path through it
HAZE_LAYER_M = 200.0
#: Koschmieder's constant: ln(1 / 0.02), the 2 % contrast threshold that defines visibility
KOSCHMIEDER = 3.912
#: the warm tint of the sky's horizon at sunrise and sunset, and its largest weight
SUNSET_HORIZON = (1.0, 0.62, 0.38)
SUNSET_HORIZON_WEIGHT = 0.55

Color = tuple[float, float, float]


# --------------------------------------------------------------------------- the sun's position
def _julian_day(when: datetime.datetime) -> float:
    """Julian day of an aware datetime (UTC)."""
    utc = when.astimezone(datetime.UTC)
    j2000 = datetime.datetime(2000, 1, 1, 12, tzinfo=datetime.UTC)
    return 2451545.0 + (utc - j2000).total_seconds() / 86400.0


def solar_position(when: datetime.datetime, latitude_deg: float, longitude_deg: float) -> tuple[float, float]:
    """The sun's apparent elevation (deg, refraction included) and azimuth (deg clockwise from north) at
    ``when`` (timezone-aware) seen from ``latitude_deg``, ``longitude_deg`` (east positive).

    NOAA's solar calculator (https://gml.noaa.gov/grad/solcalc/calcdetails.html), after Meeus,
    *Astronomical Algorithms* (1991), ch. 25."""
    if when.tzinfo is None:
        raise ValueError("solar_position needs a timezone-aware datetime")
    t = (_julian_day(when) - 2451545.0) / 36525.0  # Julian centuries since J2000
    rad = math.radians
    l0 = (280.46646 + t * (36000.76983 + t * 0.0003032)) % 360.0  # geometric mean longitude
    m = 357.52911 + t * (35999.05029 - 0.0001537 * t)  # mean anomaly
    e = 0.016708634 - t * (0.000042037 + 0.0000001267 * t)  # orbit eccentricity
    c = (
        math.sin(rad(m)) * (1.914602 - t * (0.004817 + 0.000014 * t))
        + math.sin(rad(2 * m)) * (0.019993 - 0.000101 * t)
        + math.sin(rad(3 * m)) * 0.000289
    )
    omega = 125.04 - 1934.136 * t
    apparent_long = l0 + c - 0.00569 - 0.00478 * math.sin(rad(omega))
    eps0 = 23.0 + (26.0 + (21.448 - t * (46.815 + t * (0.00059 - t * 0.001813))) / 60.0) / 60.0
    eps = eps0 + 0.00256 * math.cos(rad(omega))  # obliquity, corrected
    decl = math.asin(math.sin(rad(eps)) * math.sin(rad(apparent_long)))
    y = math.tan(rad(eps / 2.0)) ** 2
    eq_time = 4.0 * math.degrees(
        y * math.sin(2 * rad(l0))
        - 2 * e * math.sin(rad(m))
        + 4 * e * y * math.sin(rad(m)) * math.cos(2 * rad(l0))
        - 0.5 * y * y * math.sin(4 * rad(l0))
        - 1.25 * e * e * math.sin(2 * rad(m))
    )  # minutes
    utc = when.astimezone(datetime.UTC)
    minutes = utc.hour * 60.0 + utc.minute + (utc.second + utc.microsecond * 1e-6) / 60.0
    true_solar = (minutes + eq_time + 4.0 * longitude_deg) % 1440.0
    hour_angle = rad(true_solar / 4.0 - 180.0)
    lat = rad(latitude_deg)
    cos_zenith = math.sin(lat) * math.sin(decl) + math.cos(lat) * math.cos(decl) * math.cos(hour_angle)
    zenith = math.acos(max(-1.0, min(1.0, cos_zenith)))
    south = math.cos(hour_angle) * math.sin(lat) - math.tan(decl) * math.cos(lat)
    azimuth = math.degrees(math.atan2(math.sin(hour_angle), south))
    elevation = 90.0 - math.degrees(zenith)
    return elevation + _refraction(elevation), (azimuth + 180.0) % 360.0


def _refraction(elevation: float) -> float:
    """NOAA's approximate atmospheric refraction (deg) at a true elevation (deg)."""
    if elevation > 85.0:
        return 0.0
    te = math.tan(math.radians(elevation))
    if elevation > 5.0:
        arcsec = 58.1 / te - 0.07 / te**3 + 0.000086 / te**5
    elif elevation > -0.575:
        e = elevation
        arcsec = 1735.0 + e * (-518.2 + e * (103.4 + e * (-12.79 + e * 0.711)))
    else:
        arcsec = -20.772 / te
    return arcsec / 3600.0


def sun_vector(elevation_deg: float, azimuth_deg: float) -> np.ndarray:
    """Unit vector towards the sun in the Z-up ENU world (x east, y north) for an elevation and an azimuth
    clockwise from north."""
    el, az = math.radians(elevation_deg), math.radians(azimuth_deg)
    return np.array([math.cos(el) * math.sin(az), math.cos(el) * math.cos(az), math.sin(el)])


def local_time(light: LightConfig, site: SiteConfig) -> datetime.datetime:
    """The aware datetime of ``light``'s day and clock time (``time_of_day_h`` must be set), on the clock
    of ``light.utc_offset_h``, else the site's (:attr:`~droneulator.config.SiteConfig.clock_offset_h`)."""
    if light.time_of_day_h is None:
        raise ValueError("the light has no time of day")
    offset = site.clock_offset_h if light.utc_offset_h is None else light.utc_offset_h
    day = datetime.date.fromisoformat(light.date or DEFAULT_DATE)
    tz = datetime.timezone(datetime.timedelta(hours=offset))
    midnight = datetime.datetime(day.year, day.month, day.day, tzinfo=tz)
    return midnight + datetime.timedelta(hours=light.time_of_day_h)


# --------------------------------------------------------------------------- the light
@dataclass(frozen=True)
class Lighting:
    """What the renderer lights a scene with (colours multiply the texture albedo; 1.0 is full scale)."""

    #: unit vector towards the sun, Z-up world; its elevation is kept at MIN_SHADOW_ELEVATION_DEG or
    #: more (the shadow map is fitted to it); the sun's own elevation is in ``elevation_deg``
    sun: tuple[float, float, float]
    #: the direct sun on a surface facing it
    sun_color: Color
    #: hemisphere ambient of surfaces facing straight down and straight up
    ambient_ground: Color
    ambient_sky: Color
    #: sky gradient
    zenith: Color
    horizon: Color
    #: haze: extinction coefficient (1/m; 0: none) and the colour distant things fade to
    fog_beta: float = 0.0
    fog_color: Color = HAZE_COLOR
    #: the sun's true position (deg; azimuth clockwise from north); None for a scene's fixed sun
    elevation_deg: float | None = None
    azimuth_deg: float | None = None

    @property
    def fog(self) -> bool:
        return self.fog_beta > 0.0


#: the lowest elevation the light direction is given (deg): a lower sun is off anyway (SUNSET_DEG), and a
#: grazing direction would stretch the shadow map over kilometres
MIN_SHADOW_ELEVATION_DEG = 2.0


def _mix(a: Color, b: Color, t: float) -> Color:
    return (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t)


def _scale(a: Color, s: float | Color) -> Color:
    s3 = (s, s, s) if isinstance(s, float | int) else s
    return (a[0] * s3[0], a[1] * s3[1], a[2] * s3[2])


def _smoothstep(lo: float, hi: float, x: float) -> float:
    t = min(1.0, max(0.0, (x - lo) / (hi - lo)))
    return t * t * (3.0 - 2.0 * t)


def air_mass(elevation_deg: float) -> float:
    """Kasten and Young's (1989) relative air mass at an elevation (deg; clamped at the horizon)."""
    e = max(elevation_deg, 0.0)
    return 1.0 / (math.sin(math.radians(e)) + 0.50572 * (e + 6.07995) ** -1.6364)


def skylight(elevation_deg: float) -> float:
    """Diffuse skylight relative to the reference sun's: grows as the square root of the sun's height,
    fades through civil twilight, and never falls below NIGHT_SKYLIGHT."""
    floor = math.sin(math.radians(-TWILIGHT_DEG))
    e = min(max(elevation_deg, TWILIGHT_DEG), 90.0)
    ratio = (math.sin(math.radians(e)) + floor) / (math.sin(math.radians(REFERENCE_ELEVATION_DEG)) + floor)
    return max(NIGHT_SKYLIGHT, math.sqrt(max(ratio, 0.0)))


def direct_sun(elevation_deg: float) -> Color:
    """The clear-sky direct sun's colour at an elevation (deg): SUN_COLOR at the reference elevation."""
    dm = air_mass(elevation_deg) - air_mass(REFERENCE_ELEVATION_DEG)
    up = _smoothstep(SUNSET_DEG[0], SUNSET_DEG[1], elevation_deg)
    return tuple(c * math.exp(-tau * dm) * up for c, tau in zip(SUN_COLOR, SUN_OPTICAL_DEPTH, strict=True))


def historical_lighting(scene: Scene) -> Lighting:
    """The renderer's light before the light section existed: the scene's fixed sun and sky colour."""
    sun = np.asarray(scene.sun_direction, dtype=float)
    sun = sun / np.linalg.norm(sun)
    zenith = tuple(float(v) for v in scene.sky_color)
    horizon = tuple(z + (1.0 - z) * HORIZON_WHITENING for z in zenith)
    return Lighting(
        sun=(float(sun[0]), float(sun[1]), float(sun[2])),
        sun_color=SUN_COLOR,
        ambient_ground=AMBIENT_GROUND,
        ambient_sky=AMBIENT_SKY,
        zenith=zenith,
        horizon=horizon,
    )


def resolve_lighting(
    light: LightConfig | None, scene: Scene, site: SiteConfig | None = None
) -> Lighting:
    """The light of ``scene`` under ``light`` (null fields: the scene's ``light``, then the defaults);
    ``site``: the place and clock the sun is computed for unless the light names its own (normally
    ``SimConfig.site``; None: the default site). Raises ValueError for a bad scene default."""
    light = (light or LightConfig()).over(scene.light)
    base = historical_lighting(scene)
    cover = light.cloud_cover or 0.0
    beta = 0.0 if light.visibility_m is None else KOSCHMIEDER / light.visibility_m
    if light.time_of_day_h is None and cover == 0.0 and beta == 0.0:
        return base
    if light.time_of_day_h is None:
        elevation, azimuth = None, None
        sun = np.asarray(base.sun)
        sun_el = math.degrees(math.asin(sun[2]))
        sun_color, sky = base.sun_color, 1.0
        zenith, horizon = base.zenith, base.horizon
        ambient_ground, ambient_sky = base.ambient_ground, base.ambient_sky
    else:
        site = site or SiteConfig()
        lat = site.latitude_deg if light.latitude_deg is None else light.latitude_deg
        lon = site.longitude_deg if light.longitude_deg is None else light.longitude_deg
        clock = dataclasses.replace(site, longitude_deg=lon)  # without an offset: solar time where the sun is
        elevation, azimuth = solar_position(local_time(light, clock), lat, lon)
        sun_el = max(elevation, MIN_SHADOW_ELEVATION_DEG)
        sun = sun_vector(sun_el, azimuth)
        sun_color, sky = direct_sun(elevation), skylight(elevation)
        warm = SUNSET_HORIZON_WEIGHT * math.exp(-(((elevation - 2.0) / 7.0) ** 2))
        zenith = _scale(base.zenith, sky)
        horizon = _mix(_scale(base.horizon, sky), _scale(SUNSET_HORIZON, sky), warm)
        ambient_ground, ambient_sky = _scale(base.ambient_ground, sky), _scale(base.ambient_sky, sky)
    # the haze layer dims the direct sun along its slant path; that light goes diffuse, as under clouds
    slant = HAZE_LAYER_M / math.sin(math.radians(max(sun_el, MIN_SHADOW_ELEVATION_DEG)))
    diffuse = 1.0 - (1.0 - cover) * math.exp(-beta * slant)
    sun_color = _scale(sun_color, 1.0 - diffuse)
    ambient_ground = _mix(ambient_ground, _scale(OVERCAST_AMBIENT_GROUND, sky), diffuse)
    ambient_sky = _mix(ambient_sky, _scale(OVERCAST_AMBIENT_SKY, sky), diffuse)
    zenith = _mix(zenith, _scale(OVERCAST_ZENITH, sky), cover)
    horizon = _mix(horizon, _scale(OVERCAST_HORIZON, sky), cover)
    fog_color = _mix(_scale(HAZE_COLOR, sky), horizon, 0.3)
    return dataclasses.replace(
        base,
        sun=(float(sun[0]), float(sun[1]), float(sun[2])),
        sun_color=sun_color,
        ambient_ground=ambient_ground,
        ambient_sky=ambient_sky,
        zenith=zenith,
        horizon=horizon,
        fog_beta=beta,
        fog_color=fog_color,
        elevation_deg=elevation,
        azimuth_deg=azimuth,
    )
