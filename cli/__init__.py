"""Command-line shell of eol-cal: parses, calls the library, prints. No algorithms live here."""
