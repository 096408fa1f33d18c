"""What the product remembers: the SQLite episode store, its reports and exports, and the frames
kept for learning."""
