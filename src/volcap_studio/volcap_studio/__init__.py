"""The synthetic studio: an 8-camera rig rendered by ray casting with exact ground truth, as a bag
(``volcap synth``) or live (the ``synthetic_rig`` node)."""
