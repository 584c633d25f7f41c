"""The training loop and what it uses: batches, auxiliary objectives, the orthogonal loss."""
