"""The sphere S^2 at a radius: its run, certify's questions and d_{P,k}'s pieces
(``knnrefine._domains`` documents the modules every domain has)."""
