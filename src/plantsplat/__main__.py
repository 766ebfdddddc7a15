from plantsplat.cli import entry

entry()
