"""Unit conversions at the edges (reports, CLI tables, plots). Inside: kPa, ml, s, µM, mm."""

MMHG_PER_KPA = 7.50062
MS_PER_S = 1000.0


def kpa_to_mmhg(p):
    return p * MMHG_PER_KPA


def mmhg_to_kpa(p):
    return p / MMHG_PER_KPA


def s_to_ms(t):
    return t * MS_PER_S


#: How each metric is shown to people: (label, unit, converter from internal units).
METRIC_DISPLAY = {
    "EF": ("EF", "%", lambda x: 100.0 * x),
    "EDV": ("EDV", "ml", lambda x: x),
    "ESV": ("ESV", "ml", lambda x: x),
    "SV": ("SV", "ml", lambda x: x),
    "IVCT": ("IVCT", "ms", s_to_ms),
    "ET": ("ET", "ms", s_to_ms),
    "IVRT": ("IVRT", "ms", s_to_ms),
    "filling_time": ("filling", "ms", s_to_ms),
    "P_lv_peak": ("P_lv peak", "mmHg", kpa_to_mmhg),
    "P_ao_sys": ("P_ao sys", "mmHg", kpa_to_mmhg),
    "P_ao_dia": ("P_ao dia", "mmHg", kpa_to_mmhg),
    "P_ao_pulse": ("P_ao pulse", "mmHg", kpa_to_mmhg),
    "P_ao_mean": ("P_ao mean", "mmHg", kpa_to_mmhg),
    "CO": ("CO", "l/min", lambda x: x * 60.0 / 1000.0),
}
