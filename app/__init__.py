"""The Sonicverse application: the command line (app/cli), benchmarks (app/bench), the VR frame loop (app/vr),
real-time audio (app/audio_rt), the visual scene (app/scene) and task modules with their evaluation (app/tasks)."""
