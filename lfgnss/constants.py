"""Physical and system constants (IS-GPS-200, BDS-SIS-ICD, Galileo OS-SIS-ICD, GLONASS ICD)."""
from __future__ import annotations

from collections.abc import Iterable

SPEED_OF_LIGHT_M_S = 299_792_458.0
OMEGA_EARTH_RAD_S = 7.2921151467e-5          # WGS84 / GPS earth rotation rate
OMEGA_EARTH_BDS_RAD_S = 7.292115e-5          # CGCS2000
OMEGA_EARTH_GLO_RAD_S = 7.292115e-5          # PZ-90
GM_GPS_M3_S2 = 3.9860050e14
GM_GAL_M3_S2 = 3.986004418e14
GM_BDS_M3_S2 = 3.986004418e14
GM_GLO_M3_S2 = 3.9860044e14
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
GPS_L1_HZ = 1575.42e6
BDS_B1I_HZ = 1561.098e6
GAL_E1_HZ = 1575.42e6
GLO_L1_BASE_HZ = 1602.0e6
GLO_L1_STEP_HZ = 0.5625e6

#: Constellation letters of RINEX 3 in the order used for clock/ISB state layout by default.
SYSTEMS = ("G", "C", "E", "R", "J")
SYSTEM_NAMES = {"G": "GPS", "C": "BeiDou", "E": "Galileo", "R": "GLONASS", "J": "QZSS", "S": "SBAS", "I": "IRNSS"}


def unknown_systems(letters: Iterable[str]) -> str:
    """Items of ``letters`` (either case) not in ``SYSTEMS``: upper case, each once, in the order given ("" if none)."""
    return "".join(dict.fromkeys(s.upper() for s in letters if s.upper() not in SYSTEMS))
