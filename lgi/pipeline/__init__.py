"""The dataset rebuild as cached stages (the rebuild flow's library side) and the content-addressed stage cache."""
