"""Adversaries and the scripts users run: training, evaluation, search baselines, the robustness campaign, the demo."""
