"""physint_plugins: the thesis's methods, one pluggy plugin (and one folder) each.

| plugin | thesis chapter |
|---|---|
| stability | 3, ShapeStacks: visual stability prediction, stackability, stacking |
| toolsynth | 4, tool imagination (planned) |
| relate | 5, RELATE (planned) |
| geeco | 6, GEECO (planned) |
| selmo | 7, SelMo (planned) |
"""
