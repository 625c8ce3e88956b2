"""physint_plugins: the thesis's methods, one pluggy plugin (and one folder) each.

| plugin | thesis chapter |
|---|---|
| stability | 3, ShapeStacks: visual stability prediction, stackability, stacking |
| toolsynth | 4, tool imagination: a tool latent space searched for a tool that reaches |
| relate | 5, RELATE: structured GAN scenes placed by a relationship module |
| geeco | 6, GEECO: goal-conditioned visuomotor control from a target image |
| selmo | 7, SelMo (planned) |
"""
