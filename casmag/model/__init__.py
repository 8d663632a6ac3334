"""Transcription: each motion model (translational, planar, IMU) with its field map block into
one NLP (casmag.nlp)."""
