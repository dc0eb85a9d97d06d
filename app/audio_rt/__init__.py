"""Real-time audio: duplex stream, lock-free handoffs, microphone as a scene source."""
