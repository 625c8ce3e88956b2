"""geeco: goal-conditioned end-to-end visuomotor control (thesis Chapter 6)."""
