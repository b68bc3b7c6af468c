"""Phantom removal (Nagy & Benedek): pillars, 3D CNN, neighbourhood vote, reference baselines."""
