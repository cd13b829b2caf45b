"""Scene input: cameras in one convention, loaders, normalisation."""
