"""The journal: an on-disk log of the reliable topics from which restarted nodes catch up."""
