"""Every table cell's, heading's and paragraph's text (and each figure's hash) of two report.html files, diffed.

    python scripts/compare_reports.py results/before/report.html results/after/report.html

With scripts/compare_outputs.py, what shows that a change of code left a reproduction's numbers as they were:
only the generated date, timings and worker names may differ.
"""

import difflib
import hashlib
import sys
from html.parser import HTMLParser
from pathlib import Path


class Cells(HTMLParser):
    BLOCKS = ("h1", "h2", "h3", "p", "summary", "td", "th", "li")

    def __init__(self, text):
        super().__init__(convert_charrefs=True)
        self.lines, self.stack, self.table, self.row = [], [], 0, 0
        self.feed(text)

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.table += 1
            self.row = 0
        elif tag == "tr":
            self.row += 1
        if tag in self.BLOCKS:
            self.stack.append((tag, []))
        elif tag == "img":
            src = dict(attrs).get("src", "")
            self.lines.append(f"img {dict(attrs).get('alt')} sha1 {hashlib.sha1(src.encode()).hexdigest()[:12]}")

    def handle_endtag(self, tag):
        if tag in self.BLOCKS and self.stack and self.stack[-1][0] == tag:
            _, text = self.stack.pop()
            where = f"table {self.table} row {self.row} {tag}" if tag in ("td", "th") else tag
            self.lines.append(f"{where}: {' '.join(''.join(text).split())}")

    def handle_data(self, data):
        for _, text in self.stack:
            text.append(data)


def main() -> None:
    a, b = (Cells(Path(p).read_text()).lines for p in sys.argv[1:3])
    print(f"{len(a)} vs {len(b)} text items")
    diff = list(difflib.unified_diff(a, b, "before", "after", lineterm="", n=0))
    print("\n".join(diff) if diff else "no difference")


if __name__ == "__main__":
    main()
