"""The plane, a box or flat torus in two dimensions: its run, certify's questions and
d_{P,k}'s pieces (``knnrefine._domains`` documents the modules every domain has)."""
