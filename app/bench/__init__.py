"""Benchmarks behind `sonicverse bench ...`: each measures against a reference in the same run and returns a JSON-able
dict. engine: rays and audio; accuracy: error vs run time of the acoustic knobs; env: environment steps/s; vr: the
VR frame loop and live audio."""
