"""Planners of the papers, in pure JAX: obstacle avoidance by direction selection (Zhao 2018, `avoid`)."""
