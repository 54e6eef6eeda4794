"""The label page driven in a real headless browser (Playwright + Debian's chromium)."""
