"""BaS-iLQG on the tracking scene (SPEC 3.3): the foundation's end-to-end demonstration."""
