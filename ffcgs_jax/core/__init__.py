"""The foundation every layer stands on: errors, file writing, locks, config loading, version, type glossary."""
