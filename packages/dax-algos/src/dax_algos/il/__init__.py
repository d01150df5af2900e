"""Imitation learning: Transporter networks (:mod:`.transporter`) and ILD (:mod:`.ild`), and
the demonstrations they learn from (:mod:`.demos`)."""
