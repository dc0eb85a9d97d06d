"""The acoustic engine: block renderer with direct sound, HRTF, occlusion, baked reverb probes, early reflections
and late reverb. Import submodules directly: `from sonicverse_core.acoustics.renderer import AcousticRenderer`."""
