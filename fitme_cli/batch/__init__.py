"""`fitme batch`: many subjects, resumable, on local worker processes or a Ray cluster."""
