"""Parsing a request body: strict JSON and multipart, the PNG chunk check and the decode to the model's crop."""
