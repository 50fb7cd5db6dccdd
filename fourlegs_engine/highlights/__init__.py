"""highlights package."""
