"""The canonical negative phrases every relevancy score is measured against (LERF's set)."""

CANONICAL_PHRASES = ("object", "things", "stuff", "texture")
