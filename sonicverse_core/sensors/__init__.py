"""Robot sensors: RGB and depth cameras (pyrender, loaded only when a camera is asked for), binaural audio and its
spectrogram, bump, pose relative to the start, and a goal pointer."""
