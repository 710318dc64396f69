"""Judging what cellsight does against what is known: ground truth (simulator, BOP annotations),
synthetic scenes with known answers, and the reports and pictures made of it. Tests, benchmarks
and the offline reports use it; no process of a running cell does."""
