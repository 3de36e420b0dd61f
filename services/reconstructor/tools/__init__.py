"""Command-line tools of the reconstructor (pictures of stored maps, an offline end-to-end build)."""
