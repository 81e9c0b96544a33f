"""Offline evaluation of every stage against ground truth or real recordings, and its figures
(``volcap eval ...``)."""
