"""House rules: tests of the code base itself (file sizes, function length, import contracts,
the suite's layout, the reject reasons' one list, package data, the test ports and timeouts, the
generated measurements page)."""
