"""Agents: scripted baselines and learned policies (torch)."""
