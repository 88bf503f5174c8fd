#include "eval/html_report.h"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <limits>
#include <sstream>

#include "core/atomic_file.h"
#include "core/error.h"

namespace dojo::eval {

std::string html_escape(const std::string& text) {
  std::string out;
  out.reserve(text.size());
  for (char c : text) {
    switch (c) {
      case '&':
        out += "&amp;";
        break;
      case '<':
        out += "&lt;";
        break;
      case '>':
        out += "&gt;";
        break;
      case '"':
        out += "&quot;";
        break;
      default:
        out += c;
    }
  }
  return out;
}

std::string base64_encode(const std::string& bytes) {
  static const char* kAlphabet = "ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
  std::string out;
  out.reserve((bytes.size() + 2) / 3 * 4);
  size_t i = 0;
  for (; i + 2 < bytes.size(); i += 3) {
    const uint32_t v = (static_cast<uint8_t>(bytes[i]) << 16) | (static_cast<uint8_t>(bytes[i + 1]) << 8) |
                       static_cast<uint8_t>(bytes[i + 2]);
    out += kAlphabet[(v >> 18) & 63];
    out += kAlphabet[(v >> 12) & 63];
    out += kAlphabet[(v >> 6) & 63];
    out += kAlphabet[v & 63];
  }
  if (i < bytes.size()) {
    uint32_t v = static_cast<uint8_t>(bytes[i]) << 16;
    if (i + 1 < bytes.size()) v |= static_cast<uint8_t>(bytes[i + 1]) << 8;
    out += kAlphabet[(v >> 18) & 63];
    out += kAlphabet[(v >> 12) & 63];
    out += i + 1 < bytes.size() ? kAlphabet[(v >> 6) & 63] : '=';
    out += '=';
  }
  return out;
}

namespace {

std::vector<std::string> split_csv_line(const std::string& line) {
  std::vector<std::string> cells;
  std::stringstream ss(line);
  std::string cell;
  while (std::getline(ss, cell, ',')) cells.push_back(cell);
  if (!line.empty() && line.back() == ',') cells.emplace_back();
  return cells;
}

std::string read_binary(const std::filesystem::path& path) {
  std::ifstream in(path, std::ios::binary);
  DOJO_CHECK(in.good(), path.string() + ": cannot open");
  std::ostringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

std::string fmt(double v) {
  char buf[32];
  std::snprintf(buf, sizeof buf, "%.4g", v);
  return buf;
}

}  // namespace

Series read_csv_series(const std::filesystem::path& csv, const std::string& x_column,
                       const std::string& y_column, const std::string& name) {
  std::ifstream in(csv);
  DOJO_CHECK(in.good(), csv.string() + ": cannot open");
  std::string line;
  DOJO_CHECK(static_cast<bool>(std::getline(in, line)), csv.string() + ": empty (no header row)");
  const auto header = split_csv_line(line);
  auto column = [&](const std::string& c) {
    auto it = std::find(header.begin(), header.end(), c);
    DOJO_CHECK(it != header.end(), csv.string() + ": no column '" + c + "'");
    return static_cast<size_t>(it - header.begin());
  };
  const size_t xi = column(x_column), yi = column(y_column);
  Series s{name, {}, {}};
  while (std::getline(in, line)) {
    const auto cells = split_csv_line(line);
    if (cells.size() <= std::max(xi, yi) || cells[xi].empty() || cells[yi].empty()) continue;
    try {
      s.x.push_back(std::stod(cells[xi]));
      s.y.push_back(std::stod(cells[yi]));
    } catch (const std::exception&) {
      throw Error(csv.string() + ": not a number in row '" + line + "'");
    }
  }
  return s;
}

HtmlReport::HtmlReport(std::string title) : title_(std::move(title)) {}

void HtmlReport::heading(const std::string& text) { body_ += "<h2>" + html_escape(text) + "</h2>\n"; }

void HtmlReport::paragraph(const std::string& text) { body_ += "<p>" + html_escape(text) + "</p>\n"; }

void HtmlReport::table(const std::vector<std::string>& header,
                       const std::vector<std::vector<std::string>>& rows) {
  body_ += "<table><tr>";
  for (const auto& h : header) body_ += "<th>" + html_escape(h) + "</th>";
  body_ += "</tr>\n";
  for (const auto& row : rows) {
    body_ += "<tr>";
    for (const auto& c : row) body_ += "<td>" + html_escape(c) + "</td>";
    body_ += "</tr>\n";
  }
  body_ += "</table>\n";
}

void HtmlReport::video(const std::filesystem::path& mp4, const std::string& caption) {
  body_ += "<figure><video controls loop autoplay muted playsinline src=\"data:video/mp4;base64," +
           base64_encode(read_binary(mp4)) + "\"></video><figcaption>" + html_escape(caption) +
           "</figcaption></figure>\n";
}

void HtmlReport::line_chart(const std::string& title, const std::vector<Series>& series,
                            const std::string& x_label, const std::string& y_label, bool log_y, int smooth) {
  constexpr double kW = 640, kH = 300, kLeft = 60, kRight = 150, kTop = 30, kBottom = 40;
  static const char* kColors[] = {"#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b"};
  std::vector<Series> shown;
  double x0 = std::numeric_limits<double>::infinity(), x1 = -x0, y0 = x0, y1 = -x0;
  for (const auto& s : series) {
    Series t{s.name, {}, {}};
    for (size_t i = 0; i < s.y.size(); ++i) {
      // Trailing moving average: smooths the noise of single-batch losses.
      const size_t from = i + 1 >= static_cast<size_t>(std::max(smooth, 1)) ? i + 1 - std::max(smooth, 1) : 0;
      double sum = 0;
      for (size_t j = from; j <= i; ++j) sum += s.y[j];
      double y = sum / static_cast<double>(i - from + 1);
      if (log_y) {
        if (!(y > 0)) continue;
        y = std::log10(y);
      }
      if (!std::isfinite(y)) continue;
      t.x.push_back(s.x[i]);
      t.y.push_back(y);
      x0 = std::min(x0, s.x[i]);
      x1 = std::max(x1, s.x[i]);
      y0 = std::min(y0, y);
      y1 = std::max(y1, y);
    }
    shown.push_back(std::move(t));
  }
  body_ += "<h3>" + html_escape(title) + "</h3>\n";
  if (!std::isfinite(x0) || !std::isfinite(y0)) {
    body_ += "<p>(no data)</p>\n";
    return;
  }
  if (x1 == x0) x1 = x0 + 1;
  if (y1 == y0) y1 = y0 + 1;
  auto px = [&](double x) { return kLeft + (x - x0) / (x1 - x0) * (kW - kLeft - kRight); };
  auto py = [&](double y) { return kTop + (1 - (y - y0) / (y1 - y0)) * (kH - kTop - kBottom); };
  auto label_y = [&](double y) { return fmt(log_y ? std::pow(10.0, y) : y); };
  std::string svg = "<svg width=\"" + fmt(kW) + "\" height=\"" + fmt(kH) +
                    "\" xmlns=\"http://www.w3.org/2000/svg\" font-family=\"sans-serif\" font-size=\"11\">";
  svg += "<rect x=\"" + fmt(kLeft) + "\" y=\"" + fmt(kTop) + "\" width=\"" + fmt(kW - kLeft - kRight) +
         "\" height=\"" + fmt(kH - kTop - kBottom) + "\" fill=\"none\" stroke=\"#999\"/>";
  for (int i = 0; i <= 4; ++i) {  // y grid with labels
    const double y = y0 + (y1 - y0) * i / 4.0;
    svg += "<line x1=\"" + fmt(kLeft) + "\" x2=\"" + fmt(kW - kRight) + "\" y1=\"" + fmt(py(y)) + "\" y2=\"" +
           fmt(py(y)) + "\" stroke=\"#eee\"/>";
    svg += "<text x=\"" + fmt(kLeft - 4) + "\" y=\"" + fmt(py(y) + 4) + "\" text-anchor=\"end\">" +
           label_y(y) + "</text>";
  }
  svg += "<text x=\"" + fmt(kLeft) + "\" y=\"" + fmt(kH - kBottom + 15) + "\">" + fmt(x0) + "</text>";
  svg += "<text x=\"" + fmt(kW - kRight) + "\" y=\"" + fmt(kH - kBottom + 15) + "\" text-anchor=\"end\">" +
         fmt(x1) + "</text>";
  svg += "<text x=\"" + fmt((kLeft + kW - kRight) / 2) + "\" y=\"" + fmt(kH - 8) +
         "\" text-anchor=\"middle\">" + html_escape(x_label) + "</text>";
  svg += "<text x=\"12\" y=\"" + fmt((kTop + kH - kBottom) / 2) + "\" transform=\"rotate(-90 12 " +
         fmt((kTop + kH - kBottom) / 2) + ")\" text-anchor=\"middle\">" +
         html_escape(y_label + (log_y ? " (log)" : "")) + "</text>";
  for (size_t k = 0; k < shown.size(); ++k) {
    const char* color = kColors[k % 6];
    std::string points;
    for (size_t i = 0; i < shown[k].x.size(); ++i)
      points += fmt(px(shown[k].x[i])) + "," + fmt(py(shown[k].y[i])) + " ";
    svg += "<polyline fill=\"none\" stroke=\"" + std::string(color) + "\" stroke-width=\"1.5\" points=\"" +
           points + "\"/>";
    const double ly = kTop + 14.0 * static_cast<double>(k) + 6;
    svg += "<line x1=\"" + fmt(kW - kRight + 10) + "\" x2=\"" + fmt(kW - kRight + 30) + "\" y1=\"" + fmt(ly) +
           "\" y2=\"" + fmt(ly) + "\" stroke=\"" + color + "\" stroke-width=\"2\"/>";
    svg += "<text x=\"" + fmt(kW - kRight + 34) + "\" y=\"" + fmt(ly + 4) + "\">" +
           html_escape(shown[k].name) + "</text>";
  }
  svg += "</svg>\n";
  body_ += svg;
}

void HtmlReport::unit_scatter(const std::string& title, const std::vector<std::string>& labels,
                              const std::vector<double>& x, const std::vector<double>& y,
                              const std::string& x_label, const std::string& y_label) {
  constexpr double kSize = 360, kMargin = 50, kPlot = kSize - 2 * kMargin;
  const auto px = [&](double v) { return kMargin + std::clamp(v, 0.0, 1.0) * kPlot; };
  const auto py = [&](double v) { return kMargin + (1 - std::clamp(v, 0.0, 1.0)) * kPlot; };
  std::string svg = "<svg width=\"" + fmt(kSize + 160) + "\" height=\"" + fmt(kSize) +
                    "\" xmlns=\"http://www.w3.org/2000/svg\" font-family=\"sans-serif\" font-size=\"11\">";
  svg += "<rect x=\"" + fmt(kMargin) + "\" y=\"" + fmt(kMargin) + "\" width=\"" + fmt(kPlot) +
         "\" height=\"" + fmt(kPlot) + "\" fill=\"none\" stroke=\"#999\"/>";
  svg += "<line x1=\"" + fmt(px(0)) + "\" y1=\"" + fmt(py(0)) + "\" x2=\"" + fmt(px(1)) + "\" y2=\"" +
         fmt(py(1)) + "\" stroke=\"#bbb\" stroke-dasharray=\"4 3\"/>";
  for (int i = 0; i <= 4; ++i) {
    const double v = i / 4.0;
    svg += "<text x=\"" + fmt(kMargin - 4) + "\" y=\"" + fmt(py(v) + 4) + "\" text-anchor=\"end\">" + fmt(v) +
           "</text><text x=\"" + fmt(px(v)) + "\" y=\"" + fmt(kSize - kMargin + 14) +
           "\" text-anchor=\"middle\">" + fmt(v) + "</text>";
  }
  svg += "<text x=\"" + fmt(kMargin + kPlot / 2) + "\" y=\"" + fmt(kSize - 10) +
         "\" text-anchor=\"middle\">" + html_escape(x_label) + "</text>";
  svg += "<text x=\"14\" y=\"" + fmt(kMargin + kPlot / 2) + "\" transform=\"rotate(-90 14 " +
         fmt(kMargin + kPlot / 2) + ")\" text-anchor=\"middle\">" + html_escape(y_label) + "</text>";
  for (size_t i = 0; i < x.size() && i < y.size(); ++i) {
    svg += "<circle cx=\"" + fmt(px(x[i])) + "\" cy=\"" + fmt(py(y[i])) +
           "\" r=\"4\" fill=\"#1f77b4\"><title>" + html_escape(i < labels.size() ? labels[i] : "") +
           "</title></circle>";
    if (i < labels.size())
      svg += "<text x=\"" + fmt(px(x[i]) + 6) + "\" y=\"" + fmt(py(y[i]) - 4) + "\" font-size=\"9\">" +
             html_escape(labels[i]) + "</text>";
  }
  body_ += "<h3>" + html_escape(title) + "</h3>\n" + svg + "</svg>\n";
}

std::string HtmlReport::html() const {
  return "<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\"><title>" + html_escape(title_) +
         "</title>\n<style>body{font-family:sans-serif;max-width:1100px;margin:2em auto;padding:0 "
         "1em;color:#222}"
         "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px "
         "10px;text-align:right}"
         "th{background:#f4f4f4}td:first-child,th:first-child{text-align:left}"
         "figure{display:inline-block;margin:0.5em}video{image-rendering:pixelated;max-width:100%}"
         "figcaption{font-size:0.85em;color:#555}</style></head><body>\n<h1>" +
         html_escape(title_) + "</h1>\n" + body_ + "</body></html>\n";
}

void HtmlReport::write(const std::filesystem::path& path) const { write_file_atomic(path, html()); }

}  // namespace dojo::eval
