"""The registered studies: one line per study package (each defines ``STUDY``)."""

STUDIES = [
    "studies.tracking_demo",
    "studies.tracking_comparison",
    "studies.navigation",
    "studies.free_energy_bound",
    "studies.sampling_safety",
    "studies.arena",
    "studies.arena_tuning",
]
