"""The ground floor: files, images, devices, the Matches value, library errors, name suggestions;
imports nothing of the package."""
