"""Unit conversions at the edges (reports, CLI tables, plots). Inside: kPa, ml, s, µM, mm."""

MMHG_PER_KPA = 7.50062
MS_PER_S = 1000.0


def kpa_to_mmhg(p):
    return p * MMHG_PER_KPA


def mmhg_to_kpa(p):
    return p / MMHG_PER_KPA


def s_to_ms(t):
    return t * MS_PER_S

