"""The Sonicverse application: CLI, VR frame loop (app/vr), real-time audio (app/audio_rt), visual scene
(app/scene), human-study tasks (app/tasks)."""
