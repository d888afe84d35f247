"""Foundation: errors, did-you-mean, units, files, linear algebra, chunked evaluation,
compiled twins, progress."""
