"""The H2 sections of a MyST page, for the tests that check a page names what the code has."""
from __future__ import annotations


def h2_sections(text: str) -> dict[str, str]:
    """H2 title -> its text up to the next H2 (code blocks skipped when finding H2s)."""
    sections: dict[str, str] = {}
    title, fenced = None, False
    for line in text.splitlines():
        if line.startswith('```'):
            fenced = not fenced
        if not fenced and line.startswith('## '):
            title = line[3:].strip()
            sections[title] = ''
        elif title is not None:
            sections[title] += line + '\n'
    return sections
