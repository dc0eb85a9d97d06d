"""Task modules run in the VR loop (free roaming) and the evaluation of agents on the embodied tasks."""
