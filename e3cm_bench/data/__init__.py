"""Getting the data: downloads, HTTP, safe unpacking, the data folder's record."""
