"""Read-only views of the catalogue for people: lineage trees and graphs, score comparisons."""
