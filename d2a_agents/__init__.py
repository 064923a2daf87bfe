"""Agents: world model, MeanFlow policy, baselines (see the issues for the roadmap)."""
