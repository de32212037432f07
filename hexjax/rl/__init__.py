"""Reinforcement learning on the same control step: a Brax environment and Brax PPO."""
